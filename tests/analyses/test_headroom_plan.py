"""The default plan keeps >= 10 deg of joint headroom on every joint along every site's feed
and under the head motions the scenario allows (DESIGN.md section 7)."""

import json

import numpy as np

from implantplan.diagrams.arm_clearance import feed_path
from implantplan.systems import actuator
from implantplan.systems.robot import kinematics as kin
from implantplan.systems.robot import moprp


def test_every_default_site_keeps_10_deg_on_every_joint_along_its_feed(demo_plan):
    plan = json.loads((demo_plan / "plan.json").read_text())
    sc = moprp.load_scenario(plan["frames"]["scenario"], X_FT=actuator.X_FT())
    xyz = np.array(plan["base"]["xyz_in_oral"])
    X_OC = np.array(plan["frames"]["X_OC"])
    for s in plan["sites"]:
        X_OT = X_OC @ np.array(s["feeding_target"]["X_CT"])
        b = s["ik"]["branch"]
        room = np.full(6, np.inf)
        for D in moprp.head_displacements(sc):  # the identity first: the planned feed
            q = feed_path(sc, xyz, b, X_OT=D @ X_OT)
            assert np.all(np.isfinite(q)), s["name"]
            room = np.minimum(room, kin.joint_headroom(q).min(axis=0))
        assert np.all(np.rad2deg(room) >= 10.0), (s["name"], np.rad2deg(room))
        # the plan reports that smallest headroom per joint, and a passing check on it
        np.testing.assert_allclose(s["ik"]["joint_headroom"]["min_rad"], room, atol=1e-9)
        chk = [c for c in plan["checks"]
               if c["id"] == "robot.joint_headroom" and c["site"] == s["name"]]
        assert len(chk) == 1 and chk[0]["pass"] and chk[0]["limit"] == np.deg2rad(10.0)
        # the planned target configuration is the path's end
        np.testing.assert_allclose(feed_path(sc, xyz, b, X_OT=X_OT)[-1], s["ik"]["q"],
                                   atol=1e-9)
