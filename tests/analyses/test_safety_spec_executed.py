"""What the plan verified is what the feeding diagram executes: a case with a safety spec unlike
the defaults in every field is planned, the studio's teleop case is rebuilt from plan.json alone,
and every tolerance, margin and limit the diagram's systems enforce equals plan.json's."""

import json

import pytest

from implantplan.analyses.cli import main
from implantplan.analyses.live_setup import load_plan
from implantplan.diagrams.teleop import build_teleop
from implantplan.systems.safety import DEFAULT, SafetySpec
from tests.analyses.cases import default_case_data, write_case

# every field away from its default (lengths in mm, angles in deg, as the case file says)
SAFETY = {"clearance_mm": 0.8, "lateral_tolerance_mm": 0.3, "angle_tolerance_deg": 2.0,
          "registration_sigma_mm": 0.4, "registration_sigma_deg": 0.4,
          "registration_samples": 20, "alarm_margin_mm": 1.5, "barrier_rate_per_s": 15.0,
          "command_limits": {"linear_speed_mm_s": 40.0, "angular_speed_deg_s": 5.0,
                             "fault_jump_mm": 4.0, "fault_turn_deg": 2.5, "clear_after_s": 0.3}}


@pytest.fixture(scope="module")
def planned(tmp_path_factory):
    folder = tmp_path_factory.mktemp("spec")
    data = default_case_data(small=True)
    data["safety"] = SAFETY
    case = write_case(folder / "case.yaml", data)
    code = main(["plan", str(case), "--out", str(folder / "plan"), "--runs", "0",
                 "--no-figures", "--quiet"])  # the spec, not the feeds, is what is read
    assert code in (0, 3)  # the spec is recorded whether or not every check passes
    return folder / "plan"


def test_the_spec_is_written_once_and_reads_back(planned):
    plan = json.loads((planned / "plan.json").read_text())
    spec = SafetySpec.from_dict(plan["safety"])
    assert spec == SafetySpec.from_yaml(SAFETY)
    for name in ("clearance_margin", "lateral_tolerance", "angle_tolerance", "alarm_margin",
                 "barrier_rate", "command_limits"):
        assert getattr(spec, name) != getattr(DEFAULT, name), name  # the test means something


def test_the_diagram_executes_the_plans_spec(planned):
    plan = json.loads((planned / "plan.json").read_text())
    spec = SafetySpec.from_dict(plan["safety"])
    sp = load_plan(planned, reference=False)  # no percentile ranks are read
    assert sp.safety == spec
    for k, site in enumerate(plan["sites"]):
        ver = site["placement"]["verification"]
        # the region the placement verified is the spec's ...
        assert ver["lateral_tolerance"] == pytest.approx(spec.lateral_tolerance, abs=0)
        assert ver["angle_tolerance"] == pytest.approx(spec.angle_tolerance, abs=0)
        assert ver["clearance_margin"] == pytest.approx(spec.clearance_margin, abs=0)
        # ... and the fixture written beside it guards that region
        assert site["vf"]["lateral_tolerance"] == spec.lateral_tolerance
        assert site["vf"]["angle_tolerance"] == spec.angle_tolerance
        teleop = build_teleop(sp.teleop_case(k))
        vf = teleop.vf.fixture
        assert (vf.lateral_tolerance, vf.angle_tolerance) == (spec.lateral_tolerance,
                                                              spec.angle_tolerance)
        assert teleop.supervisor.barrier.margin == spec.clearance_margin
        assert teleop.supervisor.barrier.alpha == spec.barrier_rate
        assert teleop.supervisor.limits == spec.command_limits
        assert teleop.limiter.limits == spec.command_limits
        assert teleop.estimator.alarm_margin == spec.alarm_margin
