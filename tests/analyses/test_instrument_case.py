"""The case's instrument is the one the placement verifies: ``instrument: actuator`` on the
default case is placed where its head clears the scan (the PSO's optimum does not), an
instrument that cannot keep the margin is refused with the reason; the key's errors name it."""


import pytest

from implantplan.analyses import pipeline
from implantplan.analyses.case import case_from_dict, default_case_path, load_case
from implantplan.systems.errors import InputError, PlanningFailure
from implantplan.systems.files import read_yaml


def _case(**changes):
    path = default_case_path()
    data = read_yaml(path)
    data.update(changes)
    return case_from_dict(data, source=path)


def test_the_instrument_key():
    default = load_case(default_case_path())
    assert default.instrument.kind == "actuator"  # the shipped actuator, not the paper's tool
    data = read_yaml(default_case_path())
    data.pop("instrument")
    assert case_from_dict(data, source=default_case_path()).instrument.kind == "actuator"
    case = _case(instrument="actuator")
    inst = case.instrument_at(case.sites[0])
    assert inst.name == "actuator" and inst.head == pytest.approx(0.008)
    assert inst.shapes == default.instrument_at(default.sites[1]).shapes
    # the paper tool takes each site's rod and d12; on another instrument they are an error
    sites = [{**s, "rod_radius_mm": 4.0, "head_to_tip_mm": 28.0} for s in data["sites"]]
    paper = _case(instrument="paper", sites=sites)
    tool = paper.instrument_at(paper.sites[0])
    assert (tool.name, tool.rod_radius, tool.implant_length) == ("paper", 0.004, 0.028)
    for kind in ("actuator", {"urdf": "package://implantplan/tools/implanting_actuator.urdf"}):
        with pytest.raises(InputError, match=r"sites\[0\]\.rod_radius_mm: applies to "
                           "instrument: paper only"):
            _case(instrument=kind, sites=sites)
    with pytest.raises(InputError, match="instrument.kind"):
        _case(instrument="thin")
    with pytest.raises(InputError, match="instrument.urdf"):
        _case(instrument={"urdf": "no/such.urdf"})
    with pytest.raises(InputError, match="instrument.colour"):
        _case(instrument={"kind": "paper", "colour": "red"})
    urdf = "package://implantplan/tools/implanting_actuator.urdf"
    own = _case(instrument={"urdf": urdf})
    assert own.instrument_at(own.sites[0]).shapes == inst.shapes


@pytest.mark.sweep
def test_an_instrument_that_cannot_clear_the_margin_is_refused_with_its_reason():
    """A margin no placement of the actuator can keep (6 mm): refused, the search's reason and
    the optimum's clearances in the message; the paper tool at the case's margin plans."""
    case = _case(instrument="actuator", safety={**read_yaml(default_case_path())["safety"],
                                                "clearance_mm": 6.0})
    fit = pipeline.fit_stage(case)
    with pytest.raises(PlanningFailure, match="no placement clears the scan by the margin"):
        pipeline.placement_stage(case, fit)
    paper = _case(instrument="paper")
    assert all(p.valid for p in pipeline.placement_stage(paper, fit))


def _actuator_case(sites: int = 2):
    """The default case with the shipped actuator."""
    data = read_yaml(default_case_path())
    data["instrument"] = "actuator"
    data["sites"] = data["sites"][:sites]
    return case_from_dict(data, source=default_case_path())


@pytest.mark.sweep
def test_the_actuator_is_placed_where_its_head_clears_the_scan():
    """The PSO's optimum of the paper's objective puts the actuator's head in the tissue; the
    instrument search (systems.placement.planner.search_for_instrument) places it where the
    scan bound certifies the whole instrument over the feed and the fixture's region, and FCL
    at the region's samples agrees (never below the certified value)."""
    from implantplan.systems.placement.exact_clearance import ExactCavity
    from implantplan.systems.placement.tool_clearance import feed_depth, feed_poses

    case = _actuator_case(sites=1)
    fit = pipeline.fit_stage(case)
    (p,) = pipeline.placement_stage(case, fit)
    ver = p.verification
    search = ver["instrument_search"]
    margin = case.safety.clearance_margin
    assert p.valid and ver["certified_against"] == "scan"
    assert margin <= ver["clearance_certified"] <= ver["clearance_exact_min"]
    assert search["verified"] >= 1 and search["F_loss"] >= 0
    # the optimum it replaced: the actuator there is exactly in the tissue (FCL)
    rejected = search["rejected_optimum"]
    assert "below the clinical margin" in rejected["reason"]
    from implantplan.systems.placement.planner import tool_frames

    tool = case.instrument_at(case.sites[0])
    exact = ExactCavity.from_scan(fit.opened, fit.fpsm, close_open_cuts=True)
    X0 = tool_frames(p.X_CH, rejected["d_T"], rejected["theta_T"])
    P0, _ = feed_poses(X0, feed_depth(fit.fpsm, X0, tool), 0.5e-3)
    assert exact.tool_clearance(P0[0], tool).min() < 0
    # the chosen feed, every 0.5 mm, by FCL: clear by the certified value
    P, _ = feed_poses(p.X_CT, feed_depth(fit.fpsm, p.X_CT, tool), 0.5e-3)
    assert exact.tool_clearance(P[0], tool).min() >= ver["clearance_certified"]


@pytest.mark.sweep
@pytest.mark.parametrize("margin_mm,budget", [(1.7, None), (1.7, 200), (2.0, None)])
def test_a_refusal_says_whether_the_site_or_the_bound_refuses(margin_mm, budget, monkeypatch):
    """Site 36 with the actuator under a margin the worst-case region loss cannot reach. At
    1.7 mm FCL's samples keep it (1.92 mm) where the loss bound does not (1.64 mm): the
    region's branch and bound with FCL proves it and the site plans, certified >= 1.7 mm and
    below FCL's samples. With the branch and bound cut to 200 FCL queries it cannot: the
    refusal names the case as not proven, with both values and the budget. At 2 mm FCL finds
    no candidate that keeps it: the site's geometry, whatever the bound."""
    from implantplan.systems.placement import scan_clearance

    if budget is not None:
        monkeypatch.setattr(scan_clearance, "REGION_BUDGET", budget)
    data = read_yaml(default_case_path())
    case = _case(sites=data["sites"][:1], safety={**data["safety"], "clearance_mm": margin_mm,
                                                  "registration_samples": 0})
    fit = pipeline.fit_stage(case)
    margin = margin_mm * 1e-3
    if margin_mm == 1.7 and budget is None:
        (p,) = pipeline.placement_stage(case, fit)
        ver = p.verification
        region = ver["scan_bound"]["region"]
        assert region["decided"] and region["fcl_queries"] > 0
        assert margin <= ver["clearance_certified"] <= ver["clearance_exact_min"]
        return
    with pytest.raises(PlanningFailure) as info:
        pipeline.placement_stage(case, fit)
    message = str(info.value)
    best = info.value.result["verification"]["instrument_search"]["exact_best"]
    assert best["value"] <= best["feed_only"] and best["limiting_solid"] in {"head", "implant"}
    assert best["region_checked"] >= 1 and best["candidates"] > 100
    assert f"the best keeps at most {best['value'] * 1e3:.3f} mm" in message
    if margin_mm == 2.0:
        assert best["value"] < margin and "the site's geometry refuses" in message
    else:
        assert best["certified"] < margin <= best["value"]
        assert not best["region"]["decided"]
        assert f"until its budget of {best['region']['fcl_queries']} queries" in message
        assert "not proven to keep the margin" in message
