"""Benchmark: realtime factor of the feeding diagram, kinematic vs dynamic, against a bare loop.

Run: ``python -m implantplan.analyses.bench_teleop [--runs K] [--seed S]``

Prints, side by side in one run (targets from issue 6: kinematic >= 10x, dynamic >= 1x):

- the full diagram (master, fixture, FPSM estimator, DiffIK 200 Hz, tool pose, loggers) on the
  default lying case, one scripted feed per run, in kinematic mode and in dynamic mode (plant at
  1 ms under inverse dynamics control);
- the bare-loop reference: the same scene and DiffIK at 200 Hz with two trivial Python systems
  (a constant desired pose and a pass-through), no fixture, no estimator, no loggers;
- the cost share of each Python system in the kinematic run (exclusive time in its callbacks,
  measured by wrapping them), i.e. what the adapters and their numpy cores cost.

Timings on a shared machine are noisy; the ratios in one run are what to compare.
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform
from pydrake.multibody.inverse_kinematics import DifferentialInverseKinematicsIntegrator
from pydrake.systems.analysis import Simulator
from pydrake.systems.controllers import InverseDynamicsController
from pydrake.systems.framework import DiagramBuilder, LeafSystem
from pydrake.systems.primitives import StateInterpolatorWithDiscreteDerivative

from implantplan.analyses import simulate as S
from implantplan.diagrams import teleop as T
from implantplan.systems.fpsm_estimator import FpsmEstimator
from implantplan.systems.master_device import MasterDevice, feeding_runs
from implantplan.systems.vf_system import VirtualFixtureForceLaw

CALLBACKS = {
    "MasterDevice": (MasterDevice, ("_calc_velocity", "_calc_offset", "_calc_handle")),
    "VirtualFixtureForceLaw": (
        VirtualFixtureForceLaw,
        ("_update", "_calc_desired", "_calc_corrected", "_calc_violation", "_calc_force"),
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
    plant, scene_graph = T._add_scene(builder, case, mode, 0.001)
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


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=2, help="feeds per mode (default 2)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)

    sc, sc_plant = S.load_scenario("lying")
    xyz, branch, _ = S.select_layout(sc, seed=args.seed)
    case = S.make_case("lying", sc_plant, xyz, branch, S.default_instrument(args.seed))
    start = case.X_WE(case.q_start)[:3, 3]
    motions = feeding_runs(start, case.X_WTarget[:3, 3], runs=args.runs, seed=args.seed)

    rows = []
    timer = ExclusiveTimer()
    for mode in ("kinematic", "dynamic"):
        sim = wall = 0.0
        if mode == "kinematic":
            timer.patch()
        try:
            for m in motions:
                run = T.simulate(T.build_teleop(case, m, mode=mode), m.duration + S.FINISH_SECONDS)
                sim += run.sim_seconds
                wall += run.wall_seconds
        finally:
            timer.restore()
        if mode == "kinematic":
            kin_sim, kin_wall = sim, wall
        seconds = sim / len(motions)
        rows.append((mode, sim / wall, bare_loop(case, mode, seconds)))

    print(f"feeding diagram, lying default case, {args.runs} feed(s) per mode "
          f"(~{seconds:.1f} s simulated each)")
    print(f"{'mode':<10} {'full diagram':>14} {'bare loop':>11} {'full/bare':>10} {'target':>8}")
    for mode, full, bare in rows:
        target = ">= 10x" if mode == "kinematic" else ">= 1x"
        print(f"{mode:<10} {full:>13.1f}x {bare:>10.1f}x {full / bare:>10.2f} {target:>8}")
    print("issue author's bare loop on this machine: kinematic ~15x, 1 ms plant ~2.7x")
    print()
    print(
        f"Python systems in the kinematic runs ({kin_sim:.1f} s simulated, "
        f"{kin_wall:.2f} s wall):"
    )
    print(f"{'system':<24} {'calls':>8} {'us/call':>9} {'share of wall':>14}")
    total = 0.0
    for name in CALLBACKS:
        s, n = timer.seconds[name], timer.calls[name]
        total += s
        print(f"{name:<24} {n:>8d} {1e6 * s / max(n, 1):>9.1f} {100 * s / kin_wall:>13.1f}%")
    print(f"{'all Python systems':<24} {'':>8} {'':>9} {100 * total / kin_wall:>13.1f}%")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
