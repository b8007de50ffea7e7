"""The adversarial operator's motions: seeded, the speeds and directions the issue asks for."""

import numpy as np
import pytest

from implantplan.systems.errors import InputError
from implantplan.systems.teleop.adversarial_operator import KINDS, Directions, adversarial_motion

START = np.array([0.1, 0.2, 0.3])
TARGET = START + [0.0, 0.0, -0.06]  # 60 mm straight down (u_in = -z)
DIRS = Directions(u_in=np.array([0.0, 0.0, -1.0]), left=np.array([1.0, 0.0, 0.0]),
                  up=np.array([0.0, 1.0, 0.0]))


@pytest.mark.parametrize("kind", KINDS)
def test_seeded_and_starting_at_rest(kind):
    a = adversarial_motion(kind, START, TARGET, DIRS, seed=3)
    b = adversarial_motion(kind, START, TARGET, DIRS, seed=3)
    c = adversarial_motion(kind, START, TARGET, DIRS, seed=4)
    np.testing.assert_array_equal(a.p_M, b.p_M)
    assert not np.array_equal(a.p_M[: c.p_M.shape[0]], c.p_M[: a.p_M.shape[0]])
    np.testing.assert_array_equal(a.p_M[0], 0.0)


@pytest.mark.parametrize("kind, axis, sign", [("cheek_left", 0, 1), ("cheek_right", 0, -1),
                                              ("jaw", 1, -1)])
def test_pushes_at_40_mm_per_s_towards_the_wall(kind, axis, sign):
    m = adversarial_motion(kind, START, TARGET, DIRS, seed=0)
    v = m.velocity_M()
    lateral = sign * v[:, axis]
    assert lateral.max() == pytest.approx(0.040, rel=1e-9)
    pushing = lateral > 0.039
    assert 1.0 <= pushing.sum() * m.dt <= 1.5 + 1e-9  # 1-1.5 s of push
    assert abs(m.p_M[-1, axis]) >= 0.040 - 1e-9  # at least 40 mm sideways


def test_bursts_reach_2_to_5_times_the_feed_speed():
    speeds = [np.linalg.norm(adversarial_motion("bursts", START, TARGET, DIRS, seed=s)
                             .velocity_M(), axis=1).max() for s in range(8)]
    assert 0.018 <= min(speeds) and max(speeds) <= 0.05 + 0.012  # the feed's own speed adds


def test_drift_and_walk_leave_the_line():
    for kind, lo in (("drift", 0.005), ("random_walk", 0.005)):
        m = adversarial_motion(kind, START, TARGET, DIRS, seed=1)
        off = np.hypot(m.p_M[:, 0], m.p_M[:, 1]).max()
        assert off > lo
    v = adversarial_motion("random_walk", START, TARGET, DIRS, seed=1).velocity_M()
    assert np.linalg.norm(v, axis=1).max() <= 0.05 + 0.025  # capped walk + the feed


def test_unknown_kind():
    with pytest.raises(InputError, match="kind"):
        adversarial_motion("sneeze", START, TARGET, DIRS)
