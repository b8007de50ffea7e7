"""Live master inputs (keyboard, Meshcat sliders) and the LiveMasterDevice that records them."""

import numpy as np
import pytest
from pydrake.geometry import Meshcat

from implantplan.systems.errors import InputError
from implantplan.systems.frames import rot_z
from implantplan.systems.teleop.master_device import IncrementalMapping, MasterDevice
from implantplan.systems.teleop.master_input import (
    SLIDERS,
    KeyboardMaster,
    LiveMasterDevice,
    SliderMaster,
)


def test_keyboard_turn_keys_and_speed_steps():
    kb = KeyboardMaster(rate=0.1, hold=0.5)
    kb.press("roll+", 0.0)
    s = kb.sample(0.1)
    np.testing.assert_allclose(s.w_M, [0.1, 0.0, 0.0])
    np.testing.assert_allclose(s.v_M, 0.0)
    kb.press("tilt_x-", 0.2)  # two turn keys: the rate along their sum, normalised
    np.testing.assert_allclose(kb.sample(0.3).w_M, 0.1 * np.array([1.0, -1.0, 0.0]) / np.sqrt(2))
    kb.press("feed_in", 0.3)  # translation and turn keys together
    s = kb.sample(0.4)
    np.testing.assert_allclose(s.v_M, [kb.speed, 0.0, 0.0])
    assert s.buttons == {"roll+", "tilt_x-", "feed_in"}
    np.testing.assert_allclose(kb.sample(0.6).w_M, [0.0, -0.1, 0.0])  # roll+ released at 0.5
    kb.press("faster", 0.8)
    assert kb.rate == pytest.approx(0.15) and kb.speed == pytest.approx(0.0075)
    for _ in range(20):
        kb.press("faster", 0.8)
    assert kb.rate == pytest.approx(kb.max_rate) and kb.speed == pytest.approx(kb.max_speed)
    kb.press("tilt_y+", 1.0)
    kb.press("pause", 1.0)
    np.testing.assert_allclose(kb.sample(1.1).w_M, 0.0)
    with pytest.raises(InputError, match="key"):
        kb.press("spin", 0.0)


def test_slider_master_through_meshcats_api():
    meshcat = Meshcat()
    sliders = SliderMaster(meshcat)
    labels = {name: spec[0] for name, spec in SLIDERS.items()}
    assert set(labels.values()) <= set(meshcat.GetSliderNames())
    for label in labels.values():  # zero in the middle of a symmetric range
        assert meshcat.GetSliderValue(label) == 0.0
    s = sliders.sample(0.0)
    assert np.all(s.v_M == 0.0) and np.all(s.w_M == 0.0)  # at 0: no motion
    meshcat.SetSliderValue(labels["feed"], 10.0)
    meshcat.SetSliderValue(labels["lateral_y"], -2.5)
    meshcat.SetSliderValue(labels["roll"], 6.0)
    s = sliders.sample(0.1)
    np.testing.assert_allclose(s.v_M, [0.010, 0.0, -0.0025])
    np.testing.assert_allclose(s.w_M, [np.deg2rad(6.0), 0.0, 0.0])
    meshcat.SetSliderValue(labels["feed"], 500.0)  # Meshcat clamps to the slider's range
    assert sliders.sample(0.2).v_M[0] == pytest.approx(1e-3 * SLIDERS["feed"][1])
    assert sliders.values()["roll"] == 6.0
    sliders.stop()
    s = sliders.sample(0.3)
    assert np.all(s.v_M == 0.0) and np.all(s.w_M == 0.0)
    sliders.remove()
    assert not set(labels.values()) & set(meshcat.GetSliderNames())


def test_live_master_records_turns_and_the_recording_replays_them():
    """The live device's angular command is R_WM w_M (unscaled); its recording, replayed by
    MasterDevice, gives the same command at every sample."""
    kb = KeyboardMaster(speed=0.01, rate=0.2, hold=0.0475)
    mapping = IncrementalMapping(scale=0.5, R_WM=rot_z(np.pi / 2))
    dev = LiveMasterDevice(kb, mapping, dt=0.005)
    ctx = dev.CreateDefaultContext()
    V = dev.GetOutputPort("V_WE_command")
    live = []
    for k in range(40):
        if k == 0:
            kb.press("roll+", 0.0)
        if k == 20:
            kb.press("lateral_x+", 0.1)
            kb.press("tilt_y-", 0.1)
        ctx.SetTime(k * 0.005)
        live.append(np.array(V.Eval(ctx)))
    live = np.array(live)
    np.testing.assert_allclose(live[:10, :3], [[0.0, 0.2, 0.0]] * 10, atol=1e-15)  # x -> y
    np.testing.assert_allclose(live[10:20], 0.0)
    np.testing.assert_allclose(live[20:30, :3], [[0.0, 0.0, -0.2]] * 10, atol=1e-15)
    np.testing.assert_allclose(live[20:30, 3:], [[-0.005, 0.0, 0.0]] * 10, atol=1e-15)
    motion = dev.recording(0.2)
    assert motion.r_M.shape == (41, 3)
    np.testing.assert_allclose(motion.r_M[-1], [0.2 * 0.05, 0.0, -0.2 * 0.05])
    replay = MasterDevice(motion, mapping)
    rctx = replay.CreateDefaultContext()
    for k in range(40):
        rctx.SetTime(k * 0.005)
        np.testing.assert_allclose(replay.GetOutputPort("V_WE_command").Eval(rctx), live[k],
                                   atol=1e-12)


def test_a_non_finite_live_sample_is_passed_on_to_fault_not_raised():
    """A driver glitch (NaN, inf) is a command fault downstream (the CommandLimiter holds and
    logs it), not an exception that stops the diagram; the handle's integral skips it."""
    from implantplan.systems.safety import CommandLimits
    from implantplan.systems.teleop.command_limits import FAULT, NON_FINITE, classify
    from implantplan.systems.teleop.master_input import MasterSample

    class Glitchy:
        def sample(self, t):
            bad = 0.0495 < t < 0.0555  # samples 10 and 11
            v = np.array([np.nan if bad else 0.01, 0.0, 0.0])
            w = np.array([0.0, np.inf if bad else 0.0, 0.0])
            return MasterSample(v, frozenset(), w)

    dev = LiveMasterDevice(Glitchy(), dt=0.005)
    ctx = dev.CreateDefaultContext()
    out = []
    for k in range(20):
        ctx.SetTime(k * 0.005)
        out.append(np.array(dev.GetOutputPort("V_WE_command").Eval(ctx)))
    out = np.array(out)
    assert dev.non_finite_samples == 2
    assert not np.isfinite(out[10:12]).all(axis=1).any()
    assert np.isfinite(out[np.r_[0:10, 12:20]]).all()
    verdict = classify(out, CommandLimits(), 0.005)
    np.testing.assert_array_equal(verdict.status[10:12], FAULT)
    np.testing.assert_array_equal(verdict.cause[10:12], NON_FINITE)
    motion = dev.recording(0.1)  # the recording stays finite: 18 samples of 0.01 m/s
    assert np.isfinite(motion.p_M).all()
    np.testing.assert_allclose(motion.p_M[-1], [0.01 * 0.005 * 18, 0.0, 0.0], atol=1e-15)
