import numpy as np
import pytest
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import LogVectorOutput

from implantplan.systems.errors import InputError
from implantplan.systems.frames import rotation_angle
from implantplan.systems.head_motion import HeadMotion, HeadMotionSource
from implantplan.systems.tracker import Tracker, TrackerParams, camera_noise, camera_samples

PIVOT = np.array([0.2, 0.0, 0.7])


def _run(params, motion, t_end, dt=0.005):
    """Simulate source -> tracker; sample the tracker's outputs every dt."""
    X0 = np.eye(4)
    X0[:3, 3] = PIVOT
    builder = DiagramBuilder()
    src = builder.AddSystem(HeadMotionSource(motion, X0))
    trk = builder.AddSystem(Tracker(params, X0))
    builder.Connect(src.GetOutputPort("X_WHead"), trk.GetInputPort("X_WHead"))
    lost = LogVectorOutput(trk.GetOutputPort("lost"), builder, dt)
    vel = LogVectorOutput(trk.GetOutputPort("V_WHead_estimated"), builder, dt)
    diagram = builder.Build()
    sim = Simulator(diagram)
    ctx = sim.get_mutable_context()
    times = np.arange(1, int(round(t_end / dt)) + 1) * dt
    est = []
    for t in times:
        sim.AdvanceTo(t)
        est.append(trk.estimate(trk.GetMyContextFromRoot(ctx)))
    n = len(times)  # the loggers' samples at the same times (theirs start at 0)
    return (times, lost.FindLog(ctx).data()[0][1:n + 1], vel.FindLog(ctx).data().T[1:n + 1],
            np.array(est), X0)


def test_noise_is_seeded_and_has_the_stated_spread():
    p = TrackerParams(seed=7)
    ticks = np.arange(4000)
    a, b = camera_noise(p, ticks), camera_noise(p, ticks)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, camera_noise(TrackerParams(seed=8), ticks))
    np.testing.assert_allclose(a[:, 3:].std(axis=0), p.noise_position, rtol=0.08)
    np.testing.assert_allclose(a[:, :3].std(axis=0), p.noise_angle, rtol=0.08)
    X = camera_samples(p, np.repeat(np.eye(4)[None], 4000, axis=0), ticks)
    err = np.linalg.norm(X[:, :3, 3], axis=1) + p.reach * rotation_angle(X[:, :3, :3])
    assert np.mean(err > p.error_bound()) < 0.01


@pytest.mark.parametrize("rate,latency", [(30.0, 0.02), (60.0, 0.05), (40.0, 0.03)])
def test_estimate_lags_by_the_latency_at_the_camera_rate(rate, latency):
    motion = HeadMotion.make("startle", seed=1, pivot=PIVOT)
    on = motion.params["onset_s"]
    p = TrackerParams(rate=rate, latency=latency, noise_position=0.0, noise_angle=0.0)
    t, lost, V, est, X0 = _run(p, motion, on + 0.5)
    assert not lost.any()
    for k in range(0, len(t), 7):
        # the newest camera tick at or before t - latency
        tick = np.floor((t[k] - latency) * rate + 1e-6) / rate
        if tick < 0:
            np.testing.assert_allclose(est[k], X0, atol=1e-12)
            continue
        np.testing.assert_allclose(est[k], motion.D(tick)[0] @ X0, atol=1e-9)
    # the velocity estimate sees the startle (>= 30 mm/s) only after it started + latency
    speed = np.linalg.norm(V[:, 3:], axis=1)
    first = t[np.argmax(speed > 0.03)]
    assert on + latency < first < on + 0.2 + latency


def test_dropout_raises_lost_and_holds_the_last_estimate():
    motion = HeadMotion.make("breathing", seed=2, pivot=PIVOT)
    p = TrackerParams(rate=40.0, latency=0.03, dropouts=((1.0, 1.5),), seed=3)
    t, lost, V, est, X0 = _run(p, motion, 2.5)
    assert not lost[t < 1.0 + p.latency - 1e-9].any()
    assert lost[(t > 1.0 + p.latency + p.period) & (t < 1.5 + p.latency)].all()
    assert not lost[t > 1.5 + p.latency + p.period].any()
    held = est[(t > 1.0 + p.latency + p.period) & (t < 1.5 + p.latency)]
    np.testing.assert_array_equal(held, np.repeat(held[:1], len(held), axis=0))


def test_bad_settings_are_input_errors():
    with pytest.raises(InputError, match="tracker.rate"):
        TrackerParams(rate=100.0)
    with pytest.raises(InputError, match="tracker.latency"):
        TrackerParams(latency=-0.01)
    with pytest.raises(InputError, match="tracker.dropouts"):
        TrackerParams(dropouts=((2.0, 1.0),))
