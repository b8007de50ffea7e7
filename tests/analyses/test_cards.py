"""The surgeon's cards (analyses.cards): plan.json's ``cards`` agree with the plan's own
sources (recomputed here from the raw plan), report.html shows each card with plan.json's
numbers, and the verdict follows the checks and the margins."""

import copy
import html
import json
import re

import numpy as np
import pytest

from implantplan.analyses import cards
from implantplan.analyses.report import render


@pytest.fixture(scope="module")
def plan(demo_plan):
    return json.loads((demo_plan / "plan.json").read_text())


def test_every_site_has_a_card_in_plan_json_matching_its_sources(plan):
    assert [c["site"] for c in plan["cards"]] == [s["name"] for s in plan["sites"]]
    X = np.array(plan["fpsm"]["X_mesh_Center"])
    for card, s in zip(plan["cards"], plan["sites"], strict=True):
        assert card["tooth_fdi"] == int(s["name"])  # the default sites are FDI 36 and 46
        entry = X[:3, :3] @ np.array(s["hole"]["position"]) + X[:3, 3]
        axis = X[:3, :3] @ np.array(s["hole"]["axis"])
        np.testing.assert_allclose(card["entry"], entry, atol=1e-12)
        np.testing.assert_allclose(card["apex"], entry - s["placed_implant_length"] * axis,
                                   atol=1e-12)
        assert card["depth"] == s["placed_implant_length"] == pytest.approx(0.010)
        # the apex lies deeper in the jaw than the entry: against the axis into the cavity
        assert (np.array(card["apex"]) - entry) @ axis == pytest.approx(-card["depth"])
        assert np.rad2deg(card["axis_angles"]["tilt"]) == pytest.approx(15.0, abs=1e-3)
        exact = [c for c in plan["checks"]
                 if c["id"] == "placement.tool_clearance_exact" and c["site"] == s["name"]][0]
        tissue = card["instrument_to_tissue"]
        assert tissue["value"] == s["placement"]["verification"]["clearance_exact_min"]
        assert tissue["value"] == exact["value"] and tissue["margin"] == exact["margin"]
        assert card["instrument"] == plan["case"]["instrument"]["kind"] == "actuator"
        feed = s["ik"]["feed_clearance"]
        arm = card["arm_to_patient"]
        assert arm["value"] == feed["patient_distance_m"]
        if arm["value"] is None:  # nothing of the patient within the distance SceneGraph reports
            assert arm["pair"] == "" and arm["reported_within"] == feed["reported_within_m"]
        else:
            assert arm["value"] >= feed["distance_m"] and "patient::" in arm["pair"]
        assert card["p_clear_under_registration"] == s["registration"]["probability_clear"]
        assert card["feed_duration"] == max(r["sim_seconds"] for r in s["simulation"]["runs"])
        assert card["joint_headroom"] == s["ik"]["joint_headroom"]["min_rad"]
        assert card["reach"]["ik_branches_within_limits"] == \
            s["capability"]["ik_branches_within_limits"]
        assert card["verdict"] in ("ready", "tight") and card["next_step"]
        assert card["next_step"].startswith(card["verdict"] + ":")


def _card_sections(page: str) -> dict[str, str]:
    return {html.unescape(m.group(1)): html.unescape(re.sub(r"<[^>]+>", " ", m.group(2)))
            for m in re.finditer(r"<section class='card [^']*' data-site='([^']*)'>(.*?)"
                                 r"</section>", page, re.S)}


def test_the_report_opens_with_each_card_showing_plan_json_values(plan, demo_plan):
    page = (demo_plan / "report.html").read_text()
    assert page.index("class='card") < page.index("<h2>Checks</h2>")
    shown = _card_sections(page)
    assert list(shown) == [c["site"] for c in plan["cards"]]
    for card in plan["cards"]:
        text = " ".join(shown[card["site"]].split())
        assert f"tooth {card['tooth_fdi']} (FDI): {card['verdict']}" in text
        assert card["next_step"] in text
        for key in ("entry", "apex"):
            assert "(" + ", ".join(f"{1e3 * x:.1f}" for x in card[key]) + ") mm" in text
        assert f"{1e3 * card['instrument_to_tissue']['value']:.2f} mm exact (FCL)" in text
        assert f"instrument: {card['instrument']}" in text
        arm = card["arm_to_patient"]
        assert (f"> {1e3 * arm['reported_within']:.0f} mm" if arm["value"] is None
                else f"{1e3 * arm['value']:.1f} mm ({arm['pair']})") in text
        assert f"{100 * card['p_clear_under_registration']:.1f} %" in text
        assert f"{card['feed_duration']:.1f} s" in text
        assert f"{1e3 * card['depth']:.1f} mm" in text
        for j, r in enumerate(card["joint_headroom"]):
            assert f"J{j + 1} {np.rad2deg(r):.0f}" in text


def test_a_failed_check_refuses_the_site_naming_it(plan):
    broken = copy.deepcopy(plan)
    chk = next(c for c in broken["checks"] if c["id"] == "placement.tool_clearance_exact"
               and c["site"] == "46")
    chk["pass"] = False
    out = cards.surgeon_cards(broken)
    assert out[1]["verdict"] == "refused" and chk["name"] in out[1]["next_step"]
    assert out[0]["verdict"] != "refused"  # the other site's checks all pass
    page = render(broken | {"cards": out}, {})
    assert "refused: " + html.escape(chk["name"], quote=True) in page


def test_thin_margins_make_a_passing_site_tight_with_what_to_check(plan):
    thin = copy.deepcopy(plan)
    thin["sites"][0]["registration"]["probability_clear"] = 0.95
    out = cards.surgeon_cards(thin)[0]
    assert out["verdict"] == "tight" and "registration" in out["next_step"]
    ready = copy.deepcopy(plan)
    for s in ready["sites"]:
        s["ik"]["joint_headroom"]["min_rad"] = [1.0] * 6
    for c in ready["checks"]:
        if c["id"] == "robot.joint_headroom":
            c["value"], c["margin"] = 1.0, 1.0 - c["limit"]
    # the default plan's other margins are wide: with room on every joint each site is ready
    for c in cards.surgeon_cards(ready):
        assert c["verdict"] == "ready" and c["reasons"] == [], c["reasons"]
        assert c["next_step"] == "ready: " + cards.READY_STEP


def test_tooth_numbers_are_fdi_only():
    assert [cards.tooth_fdi(n) for n in ("36", "46", "11", "85", "19", "90", "site1")] == \
        [36, 46, 11, 85, None, None, None]


def test_the_card_carries_the_anatomy_with_bounds_and_verdicts(plan):
    """A mesh plan without anatomy has none on its cards; the same plan with the anatomy checks
    of a CBCT case at site 36 (a canal 1.5 mm away: fails) shows each distance with its bound
    and pass/fail in the card, in its lines (report, studio) and in plan.json's schema."""
    from implantplan import models
    from implantplan.analyses.checks import anatomy_checks

    assert all(c["anatomy"] is None for c in plan["cards"])
    assert not any(label.startswith(("implant to", "bone around"))
                   for label, _ in cards.card_lines(plan["cards"][0]))
    p = copy.deepcopy(plan)
    p["checks"] += anatomy_checks({"sites": [
        {"site": "36", "canal_clearance_m": 1.5e-3, "tooth_clearance_m": 4.0e-3,
         "nearest_implant_m": 24.7e-3, "bone_margin_m": 1.85e-3},
        {"site": "46", "canal_clearance_m": 2.8e-3, "tooth_clearance_m": 3.9e-3,
         "nearest_implant_m": 24.7e-3, "bone_margin_m": -float("inf")}]})
    c36, c46 = (cards.surgeon_card(p, k) for k in range(2))
    assert [(a["id"], a["value"], a["limit"], a["pass"]) for a in c36["anatomy"]] == [
        ("anatomy.canal_distance", 1.5e-3, 2e-3, False),
        ("anatomy.adjacent_tooth_distance", 4.0e-3, 1.5e-3, True),
        ("anatomy.inter_implant_distance", 24.7e-3, 3e-3, True),
        ("anatomy.bone_around_implant", 1.85e-3, 1e-3, True)]
    assert c36["verdict"] == "refused" and "implant to the nerve canal" in c36["next_step"]
    lines = dict(cards.card_lines(c36))
    assert lines["implant to canal"] == "1.50 mm (>= 2.0 mm): FAIL"
    assert lines["implant to adjacent tooth"] == "4.00 mm (>= 1.5 mm): pass"
    assert lines["implant to nearest implant"] == "24.70 mm (>= 3.0 mm): pass"
    assert lines["bone around implant"] == "1.85 mm (>= 1.0 mm): pass"
    assert dict(cards.card_lines(c46))["bone around implant"] == \
        "not measured (>= 1.0 mm): FAIL"  # the axis never entered bone
    page = html.unescape(render(p | {"cards": [c36, c46]}, {}))
    assert "1.50 mm (>= 2.0 mm): FAIL" in page and "1.85 mm (>= 1.0 mm): pass" in page
    jsonschema = pytest.importorskip("jsonschema")
    schema = json.loads(models.model_path("schemas/plan.schema.json").read_text())
    from implantplan.systems.files import to_jsonable  # as plan.json is written

    p["cards"] = json.loads(json.dumps(to_jsonable([c36, c46]), allow_nan=False))
    assert p["cards"][1]["anatomy"][3]["value"] is None
    jsonschema.Draft202012Validator(schema).validate(p)
    p["cards"][0]["anatomy"][0]["limit"] = None
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.Draft202012Validator(schema).validate(p)


def test_the_expected_accuracy_is_the_registration_errors_effect_on_the_implant(plan):
    """The card's expected accuracy is the plan's own registration draws applied to the
    implant: for a translation error alone the entry and apex move by |t| (mean sigma
    sqrt(8/pi), a chi distribution with 3 degrees of freedom) and the axis not at all; for a
    rotation error alone the axis turns by the rotation vector's part across it (mean sigma
    sqrt(pi/2), 2 degrees of freedom); both within the sampling error of the 1,000 draws; the
    demo plan's figures are the ones the report shows."""
    s = plan["sites"][0]
    reg = dict(s["registration"])
    entry, apex = np.array([0.01, 0.02, 0.05]), np.array([0.01, 0.012, 0.048])
    got = cards.registration_accuracy({**reg, "sigma_rotation": 0.0}, entry, apex)
    sigma = reg["sigma_translation"]
    assert got["entry"]["mean"] == pytest.approx(sigma * np.sqrt(8 / np.pi), rel=0.05)
    assert got["apex"]["mean"] == got["entry"]["mean"]  # a translation moves both alike
    assert got["angle"]["mean"] == 0.0 and got["angle"]["p95"] == 0.0
    got = cards.registration_accuracy({**reg, "sigma_translation": 0.0}, entry, apex)
    assert got["angle"]["mean"] == pytest.approx(reg["sigma_rotation"] * np.sqrt(np.pi / 2),
                                                 rel=0.05)
    card = plan["cards"][0]
    assert card["expected_accuracy"] == cards.surgeon_card(plan, 0)["expected_accuracy"]
    acc = card["expected_accuracy"]
    assert 0.5e-3 < acc["entry"]["mean"] < acc["entry"]["p95"] < 3e-3  # 0.5 mm, 0.5 deg sigmas
    line = dict(cards.card_lines(card))["expected accuracy"]
    assert f"entry {1e3 * acc['entry']['mean']:.2f}" in line and "registration" in line
