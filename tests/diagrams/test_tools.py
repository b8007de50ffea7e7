"""The implanting actuator: one definition (systems.actuator) behind diagrams.actuator_urdf' URDF
and
every other user; hand-derived frames and inertia."""

import re

import numpy as np
import pytest

from implantplan.diagrams import actuator_urdf as tools
from implantplan.systems import actuator
from implantplan.systems.errors import InputError


def test_one_definition_of_the_actuator_everywhere():
    from implantplan.diagrams.teleop import TeleopCase
    from implantplan.systems.robot.moprp import Actuator
    from implantplan.systems.teleop.fpsm_estimator import ToolLines

    assert tools.X_FT is actuator.X_FT and tools.p_FTip is actuator.p_FTip
    assert (tools.ROD_RADIUS, tools.IMPLANT_LENGTH) == (0.006, 0.031)  # seed 000 Sec. 5.2
    a = Actuator()
    assert (a.rod_length, a.rod_radius, a.head_radius, a.implant_length, a.implant_radius) == (
        actuator.ROD_LENGTH, actuator.ROD_RADIUS, actuator.HEAD_RADIUS, actuator.IMPLANT_LENGTH,
        actuator.IMPLANT_RADIUS)
    np.testing.assert_array_equal(a.X_FT(), actuator.X_FT())
    assert TeleopCase.rod_radius == actuator.ROD_RADIUS
    assert TeleopCase.implant_length == actuator.IMPLANT_LENGTH
    # Eq. 19's line2 starts d12 below the TCP; the collision model's implant ends d12 along -y
    np.testing.assert_array_equal(ToolLines.contra_angle().start_T, [[0.006, 0, 0],
                                                                     [0.006, 0, -0.031]])
    # the arm's fast collision model reads the actuator's shapes from the URDF tools writes
    # (systems.robot.arm_collision; checked shape by shape against SceneGraph in its own tests)


def test_frames_hand_derived():
    np.testing.assert_array_equal(actuator.X_FT(), [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.16],
                                                    [0, 0, 0, 1]])
    np.testing.assert_array_equal(actuator.p_FTip(0.2, 0.025), [0.0, -0.025, 0.2])
    X_FA = actuator.actuator_map_frame()
    # the mapped frame sits at the implant tip, z = drilling direction (flange -y), x = flange x
    np.testing.assert_allclose(X_FA[:3, 3], [0.0, -0.031, 0.16], atol=1e-15)
    np.testing.assert_allclose(X_FA[:3, 2], [0.0, -1.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(X_FA[:3, 0], [1.0, 0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(X_FA[:3, :3].T @ X_FA[:3, :3], np.eye(3), atol=1e-15)
    for bad in (0.0, -0.1, float("nan"), float("inf")):
        with pytest.raises(InputError, match="rod_length"):
            actuator.X_FT(bad)


def test_inertia_hand_derived():
    mass, com, inertia = tools.actuator_inertia()
    assert mass == pytest.approx(0.385)
    # centre of mass: rod at z = 0.08, head at z = 0.16, implant at (y = -0.0155, z = 0.16)
    np.testing.assert_allclose(com, [0.0, -0.005 * 0.0155 / 0.385,
                                     (0.35 * 0.08 + 0.035 * 0.16) / 0.385], rtol=1e-12)
    # I_zz: the rod's own m r^2 / 2 plus the implant's offset from the axis through the com
    y = np.array([0.0, 0.0, -0.0155]) - com[1]
    izz = 0.35 * 0.006**2 / 2 + np.sum(np.array([0.35, 0.03, 0.005]) * y**2)
    assert inertia[2, 2] == pytest.approx(izz, rel=1e-12)
    np.testing.assert_allclose(inertia, inertia.T, atol=1e-18)
    assert np.all(np.linalg.eigvalsh(inertia) > 0)
    assert inertia[0, 1] == 0.0  # the actuator is symmetric in x


def test_urdf_frames_and_parts():
    text = tools.actuator_urdf()
    assert re.search(r'<frame name="tcp" link="actuator_base" xyz="0 0 0.16"', text)
    assert re.search(r'<frame name="implant_tip" link="actuator_base" xyz="0 -0.031 0.16"', text)
    for part in ("rod", "head", "implant"):
        assert f'<visual name="{part}_visual">' in text
        assert f'<collision name="{part}_collision">' in text
    assert '<cylinder radius="0.006"' in text
    with pytest.raises(InputError, match="implant_length: expected more than half the head"):
        tools.actuator_urdf(implant_length=0.007)
    with pytest.raises(InputError, match="rod_length: expected more than the head radius"):
        tools.actuator_urdf(rod_length=0.005)
