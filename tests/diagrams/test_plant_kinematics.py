"""Drake's MultibodyPlant (built from the URDF) against the numpy kinematics core.

Acceptance: FK and Jacobians agree to 1e-9 on 10,000 random configurations. The numpy
side is one batched call; the Drake side a loop over one context (SetPositions, then
CalcRelativeTransform and two CalcJacobianSpatialVelocity calls), a few seconds in all.

Conventions checked: ``jacobian_space`` = CalcJacobianSpatialVelocity(kQDot, frame_B = flange
(or the TCP point of the flange), frame_A = base_link, frame_E = base_link), rows [w; v];
``jacobian_body`` = the same with frame_E = the flange (the TCP frame has the flange's
orientation).
"""

from __future__ import annotations

import numpy as np
import pytest

from implantplan.diagrams import actuator_urdf as tools
from implantplan.diagrams.plant import build_plant, fk_jacobian_loop
from implantplan.systems.frames import rpy_to_rotation
from implantplan.systems.robot import kinematics

N = 10_000


def _drake_batch(q: np.ndarray, X_FT: np.ndarray | None):
    diagram, plant, _, h = build_plant(scenario="arm", tool=True, limits="360")
    ctx = plant.GetMyMutableContextFromRoot(diagram.CreateDefaultContext())
    return fk_jacobian_loop(plant, ctx, h.base, h.flange, q, X_FT)


@pytest.fixture(scope="module")
def configurations():
    rng = np.random.default_rng(2026)
    return rng.uniform(-2 * np.pi, 2 * np.pi, size=(N, 6))


@pytest.mark.parametrize("with_tool", [False, True])
def test_fk_and_jacobians_agree_with_drake(configurations, with_tool):
    X_FT = tools.X_FT() if with_tool else None
    q = configurations if not with_tool else configurations[: N // 5]
    X_d, Js_d, Jb_d = _drake_batch(q, X_FT)
    X_n = kinematics.fk(q, X_FT)
    Js_n = kinematics.jacobian_space(q, X_FT)
    Jb_n = kinematics.jacobian_body(q, X_FT)
    err_X = np.abs(X_n - X_d).max()
    err_Js = np.abs(Js_n - Js_d).max()
    err_Jb = np.abs(Jb_n - Jb_d).max()
    print(
        f"tool={with_tool}: max |X| err {err_X:.2e}, |J_space| {err_Js:.2e}, |J_body| {err_Jb:.2e}"
    )
    assert err_X < 1e-9
    assert err_Js < 1e-9
    assert err_Jb < 1e-9


def test_tool_with_a_rotation():
    """A tool frame turned relative to the flange: the body Jacobian is expressed in it."""
    X_FT = np.eye(4)
    X_FT[:3, :3] = rpy_to_rotation(np.array([0.3, -0.5, 1.1]))
    X_FT[:3, 3] = [0.01, -0.02, 0.15]
    q = np.random.default_rng(8).uniform(-3, 3, size=(200, 6))
    X_d, Js_d, Jb_d = _drake_batch(q, X_FT)
    np.testing.assert_allclose(kinematics.fk(q, X_FT), X_d, atol=1e-12)
    np.testing.assert_allclose(kinematics.jacobian_space(q, X_FT), Js_d, atol=1e-12)
    np.testing.assert_allclose(kinematics.jacobian_body(q, X_FT), Jb_d, atol=1e-12)


def test_tcp_frame_of_the_plant_matches_fk_with_tool():
    diagram, plant, _, h = build_plant(scenario="lying")
    ctx = plant.GetMyMutableContextFromRoot(diagram.CreateDefaultContext())
    rng = np.random.default_rng(5)
    q = rng.uniform(-3.0, 3.0, size=(50, 6))
    X_d = np.empty((50, 4, 4))
    for i, qi in enumerate(q):
        plant.SetPositions(ctx, qi)
        X_d[i] = plant.CalcRelativeTransform(ctx, h.base, h.tcp).GetAsMatrix4()
    np.testing.assert_allclose(kinematics.fk(q, tools.X_FT()), X_d, atol=1e-12)
