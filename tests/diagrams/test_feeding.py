"""diagrams.feeding: the case builders and the cores of seed 001's feeding and error-mapping runs
(the cases are built here from systems/diagrams only, never through analyses)."""

import numpy as np
import pytest

from implantplan.diagrams import feeding as F
from implantplan.systems.errors import PlanningFailure


def test_circle_path_hand_derived():
    t, d = F.circle_path(radius=0.025, speed=0.010, dt=0.01)
    # one turn of 2 pi 25 mm at 10 mm/s: 15.71 s, starting at +Y in the Oral Y-Z plane
    assert t[-1] == pytest.approx(np.ceil(2 * np.pi * 0.025 / 0.010 / 0.01) * 0.01)
    np.testing.assert_allclose(d[0], [0.0, 0.025, 0.0])
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 0.025, rtol=1e-12)
    assert np.all(d[:, 0] == 0.0)
    np.testing.assert_allclose(np.linalg.norm(np.diff(d, axis=0), axis=1) / 0.01, 0.010,
                               rtol=1e-3)


def test_joint_error_model_is_seeded_and_sized():
    t = np.arange(200) * 0.01
    q = np.stack([np.sin(t)] * 6, axis=1)
    a = F.joint_error(q, t, np.deg2rad(0.1), 4, seed=7)
    b = F.joint_error(q, t, np.deg2rad(0.1), 4, seed=7)
    assert a.shape == (4, 200, 6) and np.array_equal(a, b)
    assert np.abs(a).max() < np.deg2rad(0.1) * 3
    assert not np.array_equal(a, F.joint_error(q, t, np.deg2rad(0.1), 4, seed=8))


def test_default_instrument_is_seed_000s_cylinder_check(cylinder_instrument):
    inst = cylinder_instrument
    # Sec. 5.3: d_T = 62.5 mm, theta_T = 0 -> the feeding target 62.5 mm above the hole along
    # the hole axis (+y), rod along +x of the Tool frame
    np.testing.assert_allclose(inst.X_CT[:3, 3], [0.0, -0.05 + 0.0625, 0.05], atol=2e-4)
    assert (inst.rod_radius, inst.implant_length) == (0.006, 0.031)


def test_layout_and_case_of_the_knee_base(cylinder_instrument):
    sc, sc_plant = F.load_scenario("lying")
    np.testing.assert_array_equal(sc_plant.X_FT, F.actuator.X_FT())
    xyz, branch, source = F.knee_layout(sc, seed=0, candidates=60)
    assert "knee of" in source and 0 <= branch < 8
    q_pre, q_target = F.layout_configurations(sc_plant, xyz, branch)
    case = F.make_case("lying", sc_plant, xyz, branch, cylinder_instrument, label="k")
    np.testing.assert_array_equal(case.q_start, q_pre)
    # the pre-feed TCP is the scenario's feed length back along the rod from the target
    d = case.X_WE(q_pre)[:3, 3] - case.X_WE(q_target)[:3, 3]
    assert np.linalg.norm(d) == pytest.approx(sc_plant.feed_length, abs=1e-9)
    with pytest.raises(PlanningFailure, match="does not reach"):
        F.make_case("lying", sc_plant, xyz + np.array([5.0, 0.0, 0.0]), branch,
                    cylinder_instrument)
