"""The studio's logic without a browser: Meshcat's API moves the sliders and clicks the buttons
(a button click is the message the browser sends, injected into the server), the studio's
``poll`` reacts; the fast verdicts are checked against SceneGraph on random bases."""

import json
import shutil

import numpy as np
import pytest

from implantplan.analyses import live_setup as ls
from implantplan.analyses import studio as st
from implantplan.analyses.cli import main
from implantplan.diagrams.arm_clearance import SceneGraphClearance
from implantplan.systems.files import read_json
from implantplan.systems.robot import moprp
from implantplan.systems.teleop.command_limits import CommandLimits
from implantplan.systems.teleop.master_device import load_csv
from implantplan.systems.teleop.master_input import KeyboardMaster, LiveMasterDevice
from implantplan.systems.teleop.supervisor import Barrier


def _str(s: str) -> bytes:
    b = s.encode()
    assert len(b) < 32
    return bytes([0xA0 | len(b)]) + b


def click(meshcat, name: str) -> None:
    """What the browser sends when a button is pressed: msgpack {type: button, name}."""
    meshcat._InjectWebsocketMessage(bytes([0x82]) + _str("type") + _str("button")
                                    + _str("name") + _str(name))


@pytest.fixture()
def plan_copy(demo_plan, tmp_path):
    """A copy of the demo plan (the studio writes into its folder)."""
    return shutil.copytree(demo_plan, tmp_path / "plan")


@pytest.fixture()
def studio(plan_copy):
    """A studio on a copy of the demo plan (each test drives its own)."""
    s, meshcat, status = st.open_studio(plan_copy, realtime_rate=0.0, scan=False)
    yield s
    status.close()


@pytest.fixture(scope="module")
def studio_plan(demo_plan, tmp_path_factory):
    """The demo plan opened once for the studio (live_setup.load_plan, its percentile reference
    included), for the tests that read it and build their own teleop runs."""
    return ls.load_plan(shutil.copytree(demo_plan, tmp_path_factory.mktemp("studio") / "plan"))


def test_layout_at_the_planned_base_is_the_plans(studio):
    plan = studio.sp.plan
    lay = studio.layout
    assert np.allclose(lay.xyz, plan["base"]["xyz_in_oral"])
    assert lay.indices.tolist() == [plan["base"]["indices_worst_over_sites"][n]
                                    for n in moprp.INDEX_NAMES]
    assert lay.percentiles.tolist() == [plan["base"]["percentiles"][n]
                                        for n in moprp.INDEX_NAMES]
    assert lay.branch.tolist() == [s["ik"]["branch"] for s in plan["sites"]]
    assert lay.confirmed and lay.clear
    sg = [c["distance"] for c in lay.confirmation]
    assert sg == pytest.approx([s["ik"]["feed_clearance"]["distance_m"] for s in plan["sites"]])
    status = studio.status()
    assert status["setup"]["feasible"] and status["mode"] == "setup"
    assert len(status["setup"]["capability_index"]) == len(plan["sites"])
    # the capability view gives the plan's answer (and what it rests on) and index
    cap = lay.capability
    for k, s in enumerate(plan["sites"]):
        assert bool(cap["map_reachable"][k]) == s["capability"]["map_reachable"]
        assert status["setup"]["capability_reachable"][k] == {
            "reachable": s["capability"]["map_reachable"],
            "answer": s["capability"]["map_answer"]}
        assert cap["index"][k] == pytest.approx(s["capability"]["voxel_index"])
        assert cap["neighbourhood_index"][k] == pytest.approx(
            s["capability"]["neighbourhood_index"])


def test_the_status_panel_shows_the_selected_sites_card_from_the_plan(studio):
    from implantplan.analyses import cards

    for k, name in enumerate(studio.sp.names):
        studio.site = k
        shown = studio.status()["card"]
        card = next(c for c in studio.sp.plan["cards"] if c["site"] == name)
        assert shown["title"] == f"tooth {name} (FDI)" and shown["verdict"] == card["verdict"]
        assert shown["next_step"] == card["next_step"]
        assert shown["lines"] == dict(cards.card_lines(card))
        assert "instrument to tissue" in shown["lines"] and "P(margin holds)" in shown["lines"]
    assert "surgeon" in st.PAGE and "s.card" in st.PAGE  # the panel draws it


def test_sliders_move_the_base_and_change_the_indices(studio):
    m = studio.meshcat
    before = studio.layout
    x0 = m.GetSliderValue(st.BASE_SLIDERS[0])
    m.SetSliderValue(st.BASE_SLIDERS[0], x0 + 20.0)
    assert studio.poll()
    after = studio.layout
    assert after.xyz[0] == pytest.approx(1e-3 * (x0 + 20.0))
    assert after.xyz[1:] == pytest.approx(before.xyz[1:], abs=1e-3)
    assert not np.array_equal(after.indices, before.indices)
    assert len(studio.latency) == 2
    # the Pareto slider puts the base on that member (to the slider's 1 mm step)
    m.SetSliderValue(st.PARETO_SLIDER, 3)
    studio.poll()
    assert studio.layout.xyz == pytest.approx(studio.sp.pareto_xyz[3], abs=6e-4)
    m.SetSliderValue(st.SITE_SLIDER, 1)
    studio.poll()
    assert studio.status()["site"] == studio.sp.names[1]


def test_keep_layout_writes_the_plan_with_the_checks_recomputed(studio, plan_copy):
    m = studio.meshcat
    m.SetSliderValue(st.BASE_SLIDERS[1], m.GetSliderValue(st.BASE_SLIDERS[1]) - 10.0)
    studio.poll()
    click(m, st.KEEP)
    studio.poll()
    plan = read_json(plan_copy / "plan.json", kind="plan")
    assert plan["base"]["xyz_in_oral"] == pytest.approx(studio.layout.xyz.tolist())
    arm = [c for c in plan["checks"] if c["id"] == "robot.arm_clearance_scene_graph"]
    assert len(arm) == len(plan["sites"])
    assert [c["value"] for c in arm] == pytest.approx(
        [c["distance"] for c in studio.layout.confirmation])
    assert plan["passed"] == all(c["pass"] for c in plan["checks"])
    assert len({c["id"] + str(c["site"]) for c in plan["checks"]}) == len(plan["checks"])


def test_quit_button_ends_the_loop(studio):
    click(studio.meshcat, st.QUIT)
    assert studio.poll() is False


def test_keyboard_teleop_feeds_to_the_fixture_stop_and_the_recording_replays(studio, plan_copy,
                                                                             tmp_path):
    m = studio.meshcat
    click(m, st.TELEOP)
    studio.poll()
    assert studio.mode == "teleop"
    feed_in = st.KEYS["feed_in"][0]
    for _ in range(3):
        click(m, st.KEYS["faster"][0])
    for i in range(160):  # 8 s simulated, the key pressed every 0.25 s (held)
        if i % 5 == 0:
            click(m, feed_in)
        studio.poll()
    s = studio.status()["teleop"]
    assert s["speed_mm_s"] == pytest.approx(5.0 * 1.5**3)
    # it went the whole feed and stopped at the fixture's end (the target), not past it
    assert s["feed_mm"] > s["feed_length_mm"] - 1.0
    assert s["feed_mm"] < s["feed_length_mm"] + 0.5
    assert s["to_target_mm"] < 1.0
    assert not s["alarm"]
    end = studio.teleop.state()["p_WE"]
    click(m, st.TELEOP)  # leaving teleop saves the run
    studio.poll()
    assert studio.mode == "setup" and len(studio.saved) == 1
    csv = studio.saved[0]
    assert csv.read_text().startswith("t_s,x_m,y_m,z_m,rx_rad,ry_rad,rz_rad\n")
    out = tmp_path / "replay"
    assert main(["simulate", "feeding", "--csv", str(csv), "--out", str(out)]) == 0
    rep = json.loads((out / "feeding.json").read_text())
    assert rep["end_difference_m"] < 1e-6
    assert np.asarray(rep["end_X_WE"])[:3, 3] == pytest.approx(end, abs=1e-6)
    # the same run written the old way (4 columns, no rotation: none was commanded) replays
    # to the same end
    old = csv.with_name("old_format.csv")
    old.write_text("".join(",".join(line.split(",")[:4]) + "\n"
                           for line in csv.read_text().splitlines()))
    shutil.copy(csv.with_suffix(".json"), old.with_suffix(".json"))
    assert main(["simulate", "feeding", "--csv", str(old), "--out", str(tmp_path / "o4")]) == 0
    rep4 = json.loads((tmp_path / "o4" / "feeding.json").read_text())
    assert np.asarray(rep4["end_X_WE"]) == pytest.approx(np.asarray(rep["end_X_WE"]), abs=1e-12)


def test_the_fixtures_force_shows_as_an_arrow_when_the_tool_is_pushed_against_its_wall(studio):
    """Feeding along the axis the fixture does not act (no arrow); held against its lateral
    wall and pushed, it resists with its damping and the orange arrow shows, pointing in."""
    m = studio.meshcat
    click(m, st.TELEOP)
    studio.poll()
    for i in range(60):  # 3 s along the axis
        if i % 5 == 0:
            click(m, st.KEYS["feed_in"][0])
        studio.poll()
    quiet = np.linalg.norm(studio.status()["teleop"]["fixture_force_N"])
    assert quiet < st.FORCE_SHOWN_N
    start = studio.teleop.state()["p_WE"]
    assert m._GetPackedProperty("/studio/force", "visible")[-1:] == b"\xc2"  # false
    forces = []
    for i in range(60):  # 3 s pushing sideways: it reaches the wall (0.5 mm) and pushes on
        if i % 5 == 0:
            click(m, st.KEYS["lateral_x+"][0])
        studio.poll()
        forces.append(studio.status()["teleop"]["fixture_force_N"])
    F = np.array(forces[-1])
    assert np.linalg.norm(F) > 4 * st.FORCE_SHOWN_N, forces[-5:]  # b * 5 mm/s = 0.5 N
    assert m._GetPackedProperty("/studio/force", "visible")[-1:] == b"\xc3"  # true
    assert m.HasPath("/studio/force/shaft") and m.HasPath("/studio/force/head")
    # it pushes back: against the sideways motion the key made
    moved = studio.teleop.state()["p_WE"] - start
    assert np.linalg.norm(moved) > 0.2e-3 and F @ moved < 0


def test_csv_replay_without_its_case_is_an_input_error(tmp_path, capsys):
    csv = tmp_path / "r.csv"
    csv.write_text("t_s,x_m,y_m,z_m\n0,0,0,0\n0.005,0,0,0\n")
    assert main(["simulate", "feeding", "--csv", str(csv), "--out", str(tmp_path / "o")]) == 2
    assert "--csv" in capsys.readouterr().err


def test_live_master_records_what_it_commanded():
    kb = KeyboardMaster(speed=0.01, hold=0.1)
    dev = LiveMasterDevice(kb, dt=0.005)
    ctx = dev.CreateDefaultContext()
    kb.press("feed_in", 0.0)
    for k in range(40):  # 0.2 s: moving for the first 0.1 s only
        ctx.SetTime(k * 0.005)
        v = dev.GetOutputPort("V_WE_command").Eval(ctx)
        assert v[3] == pytest.approx(0.01 if k < 20 else 0.0)
    motion = dev.recording(0.2)
    assert motion.p_M.shape == (41, 3)
    assert motion.p_M[-1] == pytest.approx([0.001, 0.0, 0.0])
    assert np.allclose(motion.velocity_M()[:40, 0], [0.01] * 20 + [0.0] * 20)


def test_fast_arm_clearance_never_above_scene_graph_on_random_bases(studio_plan):
    """False-safe check: the fast verdict's clearance is a lower bound of SceneGraph's at the
    same configurations, on random bases in the bounds (not designed ones)."""
    sp = studio_plan
    rng = np.random.default_rng(14)
    X = sp.sc.lower + rng.random((40, 3)) * (sp.sc.upper - sp.sc.lower)
    checked = false_safe = 0
    for xyz in X:
        lay = ls.evaluate_layout(sp, xyz)
        ok = lay.branch >= 0
        if not ok.any():
            continue
        sg = SceneGraphClearance(sp.sc, xyz)
        for k in np.flatnonzero(ok):
            d = sg(np.stack([lay.q_pre[k], lay.q[k]]), max_distance=0.2).distance.min()
            checked += 1
            assert lay.arm_clearance[k] <= d + 1e-9
            if lay.arm_clearance[k] >= sp.sc.clearance and d < sp.sc.clearance:
                false_safe += 1
    assert checked >= 10
    assert false_safe == 0


def test_studio_command_user_errors_exit_2(tmp_path, capsys):
    assert main(["studio"]) == 2
    assert "expected a case YAML or --plan DIR" in capsys.readouterr().err
    assert main(["studio", "--plan", str(tmp_path)]) == 2
    assert "--plan" in capsys.readouterr().err
    assert main(["studio", "--plan", str(tmp_path), "--port", "70000"]) == 2


def _press_for(studio, action: str, seconds: float, check=None) -> None:
    """Press a teleop key every 0.25 s (held) for ``seconds`` of simulated time."""
    for i in range(int(round(seconds / studio.teleop_step))):
        if i % 5 == 0:
            click(studio.meshcat, st.KEYS[action][0])
        studio.poll()
        if check is not None:
            check(studio.teleop.state())


def test_rotation_keys_roll_about_the_axis_tilt_held_by_the_fixture_and_replay(studio,
                                                                               tmp_path):
    """Roll turns the tool about the fixture's axis, tilt about a lateral one; the fixture holds
    both near beta of the planned orientation (it bounds the geodesic angle to R_ref), the
    supervisor keeps its margin, and the recording (7 columns) replays to the same end pose and
    orientation."""
    m = studio.meshcat
    click(m, st.TELEOP)
    studio.poll()
    case = studio.teleop.case
    beta = case.vf.angle_tolerance
    D_W = case.X_WCenter[:3, :3] @ case.vf.direction
    angles = []
    _press_for(studio, "roll+", 1.0, lambda s: angles.append(s["angle_to_plan"]))
    s = studio.teleop.state()
    assert s["roll"] == pytest.approx(beta, abs=1e-6)  # 5 deg/s for 1 s, held at beta
    assert s["tilt"] < 1e-9
    axis = s["turn_W"] / np.linalg.norm(s["turn_W"])
    assert abs(axis @ D_W) == pytest.approx(1.0, abs=1e-9)  # about the fixture's axis
    _press_for(studio, "roll-", 2.0, lambda s: angles.append(s["angle_to_plan"]))
    assert studio.teleop.state()["roll"] == pytest.approx(-beta, abs=1e-6)
    for _ in range(3):
        click(m, st.KEYS["faster"][0])
    _press_for(studio, "feed_in", 2.0)
    for action in ("tilt_x+", "tilt_y-"):
        _press_for(studio, action, 1.0, lambda s: angles.append(s["angle_to_plan"]))
        s = studio.teleop.state()
        assert s["tilt"] > 0.5 * beta  # it did tilt, up to the fixture's bound
    # held to beta, up to one control period of the commanded rate (the fixture corrects the
    # commanded pose one period ahead, to the linearization of the turn) and back within 0.2 s
    # (its return rate k / b = 20 /s)
    lag = studio.keyboard.rate * studio.teleop.device.dt
    assert max(angles) <= beta + lag + 1e-6
    assert max(angles) > beta - 1e-6
    assert angles[-1] <= beta + 1e-6
    status = studio.status()["teleop"]
    assert status["angle_to_plan_deg"] == pytest.approx(np.rad2deg(beta), abs=1e-4)
    assert not status["alarm"]
    h = studio.teleop.teleop.loggers["barrier"].FindLog(studio.teleop.context).data()[0]
    assert h.min() > Barrier().margin - 1e-4
    end = studio.teleop.state()["X_WE"]
    click(m, st.SAVE)
    studio.poll()
    csv = studio.saved[-1]
    motion = load_csv(csv)
    assert np.abs(motion.r_M).max() > 0.1  # the turns were recorded (rad, unbounded by the VF)
    out = tmp_path / "replay"
    assert main(["simulate", "feeding", "--csv", str(csv), "--out", str(out)]) == 0
    rep = json.loads((out / "feeding.json").read_text())
    assert rep["end_difference_m"] < 1e-6
    assert rep["end_angle_difference_rad"] < 1e-6
    assert np.asarray(rep["end_X_WE"]) == pytest.approx(end, abs=1e-6)


# the command limits' turning rate raised to the 20 deg/s these tests command (the default,
# 6 deg/s, would clip them: systems.safety.CommandLimits)
TURNS = CommandLimits(angular_speed=float(np.deg2rad(20.0)))


def test_without_the_fixture_a_turn_passes_and_the_supervisor_still_filters(studio_plan):
    """The rotation channel is real end to end: without the fixture a roll key turns the tool at
    the commanded rate; a tilt inside the mouth is stopped by the supervisor at its margin."""
    sp = studio_plan
    case = sp.teleop_case(0)
    kb = KeyboardMaster(speed=0.015, rate=np.deg2rad(20.0))
    live = ls.LiveTeleop(case, kb, realtime_rate=0.0, vf_enabled=False, limits=TURNS)
    for _ in range(10):  # 0.5 s at 20 deg/s outside the mouth
        kb.press("roll+", live.time)
        live.advance(0.05)
    # 20 deg/s for 0.5 s, measured one control period behind the command (DiffIK's output)
    assert np.rad2deg(live.state()["roll"]) == pytest.approx(20.0 * (0.5 - 0.005), abs=1e-3)
    kb.press("pause", live.time)
    kb.press("pause", live.time)
    for _ in range(10):
        kb.press("roll-", live.time)
        live.advance(0.05)
    kb.press("pause", live.time)  # the key's hold ends: the roll stops back at the plan's
    kb.press("pause", live.time)
    assert abs(np.rad2deg(live.state()["roll"])) < 0.5
    while live.time < 8.0 and live.state()["to_target"] > 0.5e-3:
        kb.press("feed_in", live.time)
        live.advance(0.05)
    assert live.state()["to_target"] < 0.001
    for _ in range(30):  # 30 deg commanded about a lateral axis, in the mouth
        kb.press("tilt_x+", live.time)
        live.advance(0.05)
    s = live.state()
    barrier = live.teleop.loggers["barrier"].FindLog(live.context).data()
    margin = Barrier().margin  # the default the studio builds with
    assert barrier[2].any()  # the supervisor acted
    assert barrier[0].min() > margin - 1e-4
    assert 1.0 < np.rad2deg(s["tilt"]) < 30.0  # it turned, and was stopped before 30 deg
    assert not s["alarm"]


@pytest.mark.parametrize("site,vf", [(0, True)] + [
    pytest.param(s, v, marks=pytest.mark.sweep) for s, v in ((0, False), (1, True), (1, False))])
def test_turning_in_the_mouth_checked_against_the_exact_scan_clearance(studio_plan, site, vf):
    """False-safe check of the rotation commands: at both sites, with and without the fixture
    (the default run: site 36 with it; the sweep mark the other three), feed in and then roll
    and tilt about every axis (20 deg/s, 1 s each); FCL between the whole tool and the opened
    scan (analyses.studies.scan_reference, as the adversarial study) at every logged pose never
    goes below the supervisor's margin less 0.1 mm (the arm's lag behind the desired pose the
    barrier holds), and the barrier's bound is below FCL at every logged pose (no
    false-safe)."""
    from implantplan.analyses.studies.scan_reference import exact_for, swept_clearance
    from implantplan.diagrams.teleop import CAP_BAND, X_ET
    from implantplan.systems.placement.scan_clearance import CappedScanClearance

    sp = studio_plan
    mesh = ls.opened_scan(sp)
    margin = Barrier().margin
    case = sp.teleop_case(site)
    exact = exact_for(case, mesh)
    kb = KeyboardMaster(speed=0.015, rate=np.deg2rad(20.0))
    live = ls.LiveTeleop(case, kb, realtime_rate=0.0, vf_enabled=vf, limits=TURNS)
    while live.time < 5.0:
        kb.press("feed_in", live.time)
        live.advance(0.05)
    for key in ("tilt_x+", "tilt_y-", "roll+", "tilt_x-", "tilt_y+"):
        for _ in range(20):
            kb.press(key, live.time)
            live.advance(0.05)
    h = live.teleop.loggers["barrier"].FindLog(live.context).data()[0]
    q = live.teleop.loggers["q"].FindLog(live.context).data().T[:, :6]
    X_CT = np.linalg.inv(case.X_WCenter) @ case.X_WE(q) @ X_ET
    # FCL's smallest over the logged poses (measured where it can be the smallest)
    d = swept_clearance(case, exact, q, screen=True).at_poses
    assert len(d) == len(h) > 1900
    assert h.min() > margin - 1e-4
    # the arm lags the desired pose the barrier holds: the measured poses keep the margin less
    # 0.1 mm (the criterion: margin - 0.2 mm)
    assert d.min() > margin - 1e-4, (sp.names[site], vf, d.min())
    # false-safe: the barrier's own bound (the capped scan bound) at the same poses against its
    # exact reference, FCL of the same solids on the scan the plan cut
    assert case.scan is not None
    b = CappedScanClearance(case.scan, margin + CAP_BAND)(X_CT)
    ref = case.scan.exact.tool_clearance(X_CT, case.tool)
    assert int(np.sum((b >= margin) & (ref < margin))) == 0
    assert np.all(b <= ref + 1e-9)
    assert not live.state()["alarm"]


def test_slider_master_drives_teleop_and_switches_with_the_keyboard(studio):
    from implantplan.systems.teleop.master_input import SLIDERS

    m = studio.meshcat
    click(m, st.MASTER)
    studio.poll()
    assert studio.master == "sliders" and studio.status()["master"] == "sliders"
    assert m.GetSliderValue(SLIDERS["feed"][0]) == 0.0  # there from the start, at 0
    click(m, st.TELEOP)
    studio.poll()
    assert studio.mode == "teleop" and studio.sliders is not None
    start = studio.teleop.state()
    for _ in range(10):  # the sliders at 0: no motion
        studio.poll()
    s = studio.teleop.state()
    assert np.linalg.norm(s["p_WE"] - start["p_WE"]) < 1e-9 and s["tilt"] < 1e-12
    m.SetSliderValue(SLIDERS["feed"][0], 10.0)
    m.SetSliderValue(SLIDERS["roll"][0], 2.0)
    for _ in range(20):  # 1 s at 10 mm/s and 2 deg/s
        studio.poll()
    s = studio.teleop.state()
    assert s["feed"] == pytest.approx(0.010, abs=1e-4)
    assert s["roll"] == pytest.approx(studio.teleop.case.vf.angle_tolerance, abs=1e-6)
    assert studio.status()["teleop"]["sliders"]["feed"] == 10.0
    click(m, st.KEYS["pause"][0])  # P: the sliders back to zero, the tool stops
    studio.poll()
    assert m.GetSliderValue(SLIDERS["feed"][0]) == 0.0
    before = studio.teleop.state()["p_WE"]
    for _ in range(5):
        studio.poll()
    assert np.linalg.norm(studio.teleop.state()["p_WE"] - before) < 1e-9
    click(m, st.MASTER)  # back to the keyboard during the run
    studio.poll()
    assert studio.master == "keyboard"
    assert m.GetSliderValue(SLIDERS["feed"][0]) == 0.0  # back to 0: they do not drive now
    for _ in range(4):
        click(m, st.KEYS["feed_in"][0])
        studio.poll()
    assert studio.teleop.state()["feed"] > s["feed"] + 0.0005
    click(m, st.TELEOP)
    studio.poll()
    motion = load_csv(studio.saved[-1])  # one recording of both masters
    assert motion.p_M[-1, 0] > 0.0105 and motion.r_M[:, 0].max() > 0.03


def test_fpsm_slices_toggle(studio):
    m = studio.meshcat
    path = studio.slices_path
    assert m.HasPath(path + "/slice_0")  # drawn even without the scan

    def visible() -> bool:
        packed = m._GetPackedProperty(path, "visible")  # msgpack: ... value true/false
        assert packed, "no visible property set"
        return {b"\xc3": True, b"\xc2": False}[packed[-1:]]

    click(m, st.SLICES)
    studio.poll()
    assert not visible() and studio.status()["fpsm_slices"] is False
    click(m, st.TELEOP)  # in teleop mode too
    studio.poll()
    click(m, st.SLICES)
    studio.poll()
    assert visible() and studio.slices_visible
    assert any("FPSM slices" in line for line in studio.status()["keys"])
