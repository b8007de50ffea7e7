"""The feeding diagram: a full feed on the default case, a bad command stream, both modes."""

import numpy as np
import pytest

from implantplan.diagrams import feeding as S
from implantplan.diagrams.teleop import X_ET, ToolPose, build_teleop, simulate
from implantplan.systems.teleop.master_device import MasterMotion, feeding_runs


@pytest.fixture(scope="module")
def case(knee_case):
    return knee_case


def test_tool_pose_matches_the_kinematics_core(case):
    """ToolPose (Drake's plant: URDF base weld + actuator tcp frame) against the numpy FK with
    diagrams.actuator_urdf.X_FT and the layout's base pose."""
    motion = MasterMotion(dt=0.01, p_M=np.zeros((2, 3)))
    teleop = build_teleop(case, motion)
    system = ToolPose(teleop.plant, teleop.plant.GetFrameByName("tcp"))
    context = system.CreateDefaultContext()
    rng = np.random.default_rng(0)
    for q in [case.q_start, *rng.uniform(-3, 3, (5, 6))]:
        system.GetInputPort("q").FixValue(context, q)
        X = system.GetOutputPort("X_WE").Eval(context).GetAsMatrix4()
        np.testing.assert_allclose(X, case.X_WE(q), atol=1e-12)
        np.testing.assert_allclose(system.GetOutputPort("p_WE").Eval(context), X[:3, 3])


def test_target_frame_is_the_tool_frame_at_the_goal(case):
    # seed 000's Tool x (the rod, out of the mouth) is End -z; Tool z (implant axis) is End y
    X_WE = case.X_WE_target
    np.testing.assert_allclose(X_WE @ X_ET, case.X_WTarget, atol=1e-12)
    np.testing.assert_allclose(X_WE[:3, 2], -case.X_WTarget[:3, 0], atol=1e-12)
    # the start is backed out along the rod, 60 mm (the scenario's feed length)
    d = case.X_WE(case.q_start)[:3, 3] - case.X_WTarget[:3, 3]
    np.testing.assert_allclose(d, 0.06 * case.X_WTarget[:3, 0], atol=1e-9)


def test_full_feed_reaches_the_target_inside_the_fixture_without_alarm(case):
    start = case.X_WE(case.q_start)[:3, 3]
    target = case.X_WTarget[:3, 3]
    motion = feeding_runs(start, target, runs=1, seed=4)[0]
    run = simulate(build_teleop(case, motion), motion.duration + S.FINISH_SECONDS)
    assert np.linalg.norm(run.p_WE[-1] - target) < 0.001
    assert run.violation.max() < 0.001
    assert not run.alarm.any()
    assert 0.0 < run.min_d_safe.min() < 1.0  # the estimator saw the rod inside the mouth
    assert run.joint_travel > 0.1  # a 60 mm feed moves the joints by tenths of a radian
    # bit-for-bit repeatable
    again = simulate(build_teleop(case, motion), motion.duration + S.FINISH_SECONDS)
    assert np.array_equal(again.q, run.q)


def test_one_diagram_serves_every_run_of_a_case(case):
    """The motion is a context parameter: two runs on one diagram, in either order, give the
    same logs bit for bit as a diagram built for each motion (the pre-change behaviour)."""
    start = case.X_WE(case.q_start)[:3, 3]
    target = case.X_WTarget[:3, 3]
    m0, m1 = feeding_runs(start, target, runs=2, seed=7)
    assert m0.p_M.shape != m1.p_M.shape or not np.array_equal(m0.p_M, m1.p_M)
    shared = build_teleop(case)
    T = max(m0.duration, m1.duration) + S.FINISH_SECONDS
    on_shared = [simulate(shared, T, motion=m) for m in (m1, m0, m1)]
    own = [simulate(build_teleop(case, m), T) for m in (m1, m0)]
    for a, b in ((on_shared[0], own[0]), (on_shared[1], own[1]), (on_shared[2], own[0])):
        assert np.array_equal(a.q, b.q)
        assert np.array_equal(a.min_d_safe, b.min_d_safe)
    assert not np.array_equal(on_shared[0].q, on_shared[1].q)  # the runs really differ
    # the default context keeps the built motion; a run's context holds its own
    assert shared.master.motion.duration == 1.0  # systems.teleop.master_device.STILL
    context = shared.diagram.CreateDefaultContext()
    shared.master.set_motion(context, m0)
    assert shared.master.motion_in(context) is m0


def cheek_push(case, *, depth=0.03, lateral=0.06, speed=0.02, dt=0.005):
    """Feed straight in by ``depth`` then push sideways into the cheek (Center +x)."""
    start = case.X_WE(case.q_start)[:3, 3]
    u_in = -case.X_WTarget[:3, 0]  # into the mouth along the rod
    u_cheek = case.X_WCenter[:3, 0]
    n1 = int(depth / speed / dt)
    n2 = int(lateral / speed / dt)
    s1 = np.linspace(0.0, depth, n1)
    s2 = np.linspace(0.0, lateral, n2)[1:]
    path = np.concatenate(
        [start + s1[:, None] * u_in, start + depth * u_in + s2[:, None] * u_cheek]
    )
    return MasterMotion(dt=dt, p_M=path - start)


def test_bad_command_into_the_cheek(case):
    motion = cheek_push(case)
    duration = motion.duration + 0.5
    guarded = simulate(build_teleop(case, motion, finish=False), duration)
    # the fixture stops the tool: it stays within 1 mm of the fixture and never touches
    assert guarded.violation.max() < 0.001
    assert guarded.min_d_safe.min() > 0.0
    lateral = (guarded.p_WE - guarded.p_WE[0]) @ case.X_WCenter[:3, 0]
    assert lateral.max() < case.vf.cylinder_radius + 0.001

    free = simulate(build_teleop(case, motion, finish=False, vf_enabled=False,
                                 supervisor_enabled=False), duration)
    contact = np.flatnonzero(free.min_d_safe <= 0.0)
    assert contact.size, "without the fixture and the supervisor the push must reach the cheek"
    t_contact = free.t_safety[contact[0]]
    t_alarm = free.first_alarm_time()
    assert t_alarm is not None and t_alarm < t_contact

    # the supervisor alone (no fixture) stops the push at its margin (1 mm of FPSM clearance)
    barrier_only = simulate(build_teleop(case, motion, finish=False, vf_enabled=False), duration)
    h = barrier_only.barrier[:, 0]
    assert barrier_only.barrier[:, 2].any()  # it acted
    assert h.min() > 0.001 - 1e-4
    assert barrier_only.min_d_safe.min() > 0.0


def test_dynamic_mode_tracks_the_kinematic_run(case):
    start = case.X_WE(case.q_start)[:3, 3]
    u_in = -case.X_WTarget[:3, 0]
    motion = feeding_runs(start, start + 0.02 * u_in, runs=1, seed=1)[0]
    kinematic = simulate(build_teleop(case, motion, finish=False), 2.0)
    dynamic = simulate(build_teleop(case, motion, finish=False, mode="dynamic"), 2.0)
    assert np.abs(dynamic.p_WE - kinematic.p_WE).max() < 0.001
    assert dynamic.violation.max() < 0.001


def test_bad_mode_is_an_input_error(case):
    from implantplan.systems.errors import InputError

    with pytest.raises(InputError, match="mode"):
        build_teleop(case, MasterMotion(dt=0.01, p_M=np.zeros((2, 3))), mode="fast")


def test_dynamic_mode_has_contact_with_the_moprp_environment(case):
    """One model of the room: the dynamic plant checks the arm against the scenario's patient,
    chair and cart (not filtered away), and the selected layout's feed never touches them."""
    from pydrake.geometry import Role

    from implantplan.diagrams import plant as scene

    start = case.X_WE(case.q_start)[:3, 3]
    target = case.X_WTarget[:3, 3]
    motion = feeding_runs(start, target, runs=1, seed=4)[0]
    teleop = build_teleop(case, motion, mode="dynamic")
    run = simulate(teleop, motion.duration + S.FINISH_SECONDS)
    assert np.linalg.norm(run.p_WE[-1] - target) < 0.001
    sg, plant = teleop.scene_graph, teleop.plant
    inspector = sg.model_inspector()
    proximity = inspector.GetAllGeometryIds(Role.kProximity)
    env = [g for g in proximity
           if inspector.GetName(inspector.GetFrameId(g)) in ("patient::patient", "cart::cart")]
    by_name = {inspector.GetName(g): g for g in proximity}
    assert len(env) == 6  # head, torso, legs, chair, chair_column, cart
    assert not inspector.CollisionFiltered(by_name["aubo::wrist1_Link_collision_0"],
                                           by_name["patient::head"])
    assert inspector.CollisionFiltered(by_name["actuator::rod_collision"],
                                       by_name["patient::head"])
    context = teleop.diagram.CreateDefaultContext()
    pc = plant.GetMyMutableContextFromRoot(context)
    sgc = sg.GetMyContextFromRoot(context)
    for q in run.q[:: max(1, len(run.q) // 20)]:
        plant.SetPositions(pc, plant.GetModelInstanceByName("aubo"), q)
        query = sg.get_query_output_port().Eval(sgc)
        assert query.ComputePointPairPenetration() == []
        assert scene.environment_distance(query, inspector, env, 1.0) > 0.005


def _feed_in(case, depth=0.03, speed=0.01, dt=0.005):
    """Straight in along the rod by ``depth`` at ``speed`` (displacements from the start)."""
    u_in = -case.X_WTarget[:3, 0]
    n = int(round(depth / speed / dt))
    return np.arange(n + 1)[:, None] * (speed * dt) * u_in


@pytest.mark.parametrize("back", [False, True])
def test_a_200_mm_jump_of_the_handle_is_a_fault_not_a_motion(case, back):
    """The handle's reading jumps 200 mm towards the cheek in one 5 ms sample (and stays, or
    comes back at the next): a command of 40 m/s. It is a logged fault at that sample, the tool
    holds where it was (the arm does not move beyond the one step it was finishing), and no
    step of the arm exceeds the speed limit's 0.25 mm per period."""
    d = _feed_in(case)
    k = d.shape[0]  # the jump's sample
    hold = np.repeat(d[-1:], 200, axis=0)  # 1 s still
    p = np.concatenate([d, hold])
    jump = 0.2 * case.X_WCenter[:3, 0]
    if back:
        p[k] += jump
    else:
        p[k:] += jump
    motion = MasterMotion(dt=0.005, p_M=p)
    teleop = build_teleop(case, motion, finish=False)
    run = simulate(teleop, motion.duration)
    assert run.fault_events == 1
    expected = [k - 1, k] if back else [k - 1]  # the velocity of sample i is p[i+1] - p[i]
    np.testing.assert_allclose(run.fault_times, np.array(expected) * 0.005, atol=1e-9)
    steps = np.linalg.norm(np.diff(run.p_WE, axis=0), axis=1)
    limit = teleop.limiter.limits.linear_speed * teleop.period
    assert steps.max() <= 1.1 * limit
    after = run.t >= (k - 1) * 0.005
    moved = np.linalg.norm(run.p_WE[after] - run.p_WE[after][0], axis=1).max()
    assert moved < 3 * 0.01 * 0.005  # at most the calm steps in flight when the jump came
    assert run.violation.max() < 0.0005


@pytest.mark.parametrize("V", [[0, 0, 0, 1e9, 0, 0], [0, 0, 0, np.nan, 0, 0],
                               [0, 0, 0, 0, -np.inf, 0], [1e9, 0, 0, 0, 0, 0]],
                         ids=["1e9 m/s", "NaN", "-inf", "1e9 rad/s"])
def test_an_absurd_command_is_a_logged_fault_with_no_motion(case, V):
    """The device reports an absurd twist for 3 samples mid-feed: the limiter holds the command
    at zero from the first (a logged fault at its time), the tool stays where it was, and the
    feed resumes at the 40th clean sample (0.2 s) without a jump of the arm."""
    from implantplan.systems.teleop.master_device import GlitchedMotion

    d = _feed_in(case, depth=0.04)
    k = d.shape[0] // 2
    glitch = GlitchedMotion(MasterMotion(dt=0.005, p_M=d), np.arange(k, k + 3),
                            np.tile(np.asarray(V, dtype=float), (3, 1)))
    teleop = build_teleop(case, finish=False)
    run = simulate(teleop, glitch.duration + 0.5, motion=glitch)
    assert run.fault_events == 1
    np.testing.assert_allclose(run.fault_times, np.arange(k, k + 3) * 0.005, atol=1e-9)
    held = (run.t >= k * 0.005) & (run.t <= (k + 2 + 40) * 0.005)
    p = run.p_WE[held]
    assert np.linalg.norm(p - p[0], axis=1).max() < 3 * 0.01 * 0.005
    steps = np.linalg.norm(np.diff(run.p_WE, axis=0), axis=1)
    assert steps.max() <= 1.1 * 0.01 * 0.005  # never faster than the calm feed: no jump
    # the feed went on after the hold: the tool moved in by the feed less the held 0.21 s
    moved_in = (run.p_WE[-1] - run.p_WE[0]) @ -case.X_WTarget[:3, 0]
    assert moved_in == pytest.approx(0.04 - 0.01 * 42 * 0.005, abs=1e-5)  # 3 bad + 39 held
