"""``implantplan analyze accuracy`` (analyses.studies.accuracy) on the demo plan: all sources off
places the implant on the plan, registration alone reproduces the registration Monte Carlo's
spread, the same seed gives the same table, bad flags exit 2 before any planning."""

import json

import numpy as np
import pytest
from scipy import stats

from implantplan.analyses.studies import accuracy as A
from implantplan.systems.placement.exact_clearance import registration_errors
from implantplan.systems.teleop.insertion import implant_deviation
from tests.conftest import run_cli


@pytest.fixture(scope="module")
def sites(demo_plan):
    return A.sites_of(plan=demo_plan, approach=A.APPROACH_MM * 1e-3)


def _full_depth(sites):
    """The sites whose nominal run reaches the planned depth (the others are reported with the
    depth they reached: a joint limit on the insertion, not an error source)."""
    out = []
    for s in sites:
        sim = A.Simulations(s, 0)
        dev = A.deviations(sim, (), 1)
        out.append((s, sim, dev))
    return out


def test_all_sources_off_places_the_implant_on_the_plan(sites):
    reached = 0
    for site, _, dev in _full_depth(sites):
        if abs(dev["depth_reached"][0] - site.plan.depth) > 1e-6:
            continue  # stalled: its budget says so (depth_reached_mm)
        reached += 1
        assert dev["entry"][0] < 1e-6 and dev["apex"][0] < 1e-6, site.label
        assert dev["angle"][0] < 1e-6, site.label
    assert reached >= 1  # at least one site of the demo plan inserts to its planned depth


def test_registration_alone_reproduces_the_monte_carlos_spread(sites):
    site = sites[-1]
    sim = A.Simulations(site, 0)
    runs = 200
    dev = A.deviations(sim, ("registration",), runs)
    assert sim.simulations == 1  # the registration is composed after one simulation
    # the Monte Carlo's own draws (its sampler, another stream) applied to the same placement
    X = sim.cache[A.run_key((), 0)]
    E_inv = registration_errors(site.case.safety, np.random.default_rng(12345), 20000)
    ref = implant_deviation(E_inv @ X, site.plan)
    for k in ("entry", "apex", "angle"):
        a, b = dev[k], ref[k]
        # the mean within 4 standard errors, and the same distribution (KS)
        se = b.std() / np.sqrt(runs)
        assert abs(a.mean() - b.mean()) < 4 * se, (k, a.mean(), b.mean(), se)
        assert abs(a.std() - b.std()) < 0.2 * b.std(), (k, a.std(), b.std())
        assert stats.ks_2samp(a, b).pvalue > 1e-3, k
    # and the spread scales with the sigma (a sampler that ignored it fails here)
    twice = A.deviations(sim, ("registration",), runs, registration_scale=2.0)
    assert twice["entry"].mean() == pytest.approx(2 * dev["entry"].mean(), rel=0.05)


def test_the_same_seed_gives_the_same_table(sites):
    site = sites[-1:]
    kw = dict(sources=("registration", "operator"), runs=1, sensitivity_runs=0)
    a = A.table(A.accuracy_study(site, seed=3, **kw))
    b = A.table(A.accuracy_study(site, seed=3, **kw))
    assert a == b
    c = A.table(A.accuracy_study(site, seed=4, **kw))
    assert [r["entry_mean"] for r in c] != [r["entry_mean"] for r in a]


def test_the_command_writes_the_table_figures_and_json(demo_plan, tmp_path):
    out = tmp_path / "acc"
    code, printed = run_cli(["analyze", "accuracy", "--plan", str(demo_plan), "--runs", "1",
                             "--sources", "registration,operator", "--sensitivity-runs", "0",
                             "--workers", "1", "--quiet", "--out", str(out)])
    assert code == 0, printed
    data = json.loads((out / "accuracy.json").read_text())
    assert data["kind"] == "accuracy" and data["schema_version"] == 1
    rows = {(r["site"], r["row"]) for r in data["table"]}
    for label in data["sites"]:
        assert {(label, n) for n in ("none", "registration", "operator", "all")} <= rows
    for f in data["figures"]:
        assert (out / f).is_file()
    assert "Yomi (haptic robot)" in data["clinical"]
    # a second run into the same study folder is allowed, into a foreign folder not
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    code, printed = run_cli(["analyze", "accuracy", "--plan", str(demo_plan), "--runs", "1",
                             "--out", str(foreign)])
    assert code == 2 and "--out" in printed
    assert (foreign / "notes.txt").read_text() == "mine"


def test_the_insertion_clearance_starts_free_at_the_target(sites, demo_plan):
    """The instrument without its implant, at the feeding target, keeps at least the exact
    clearance the plan verified for the whole instrument along the feed (another cut of the
    same scan: 0.3 mm of tolerance), and the clearance is reported along the whole stroke."""
    plan = json.loads((demo_plan / "plan.json").read_text())
    for site, planned in zip(sites, plan["sites"], strict=True):
        c = A.insertion_clearance(site, samples=5)
        assert c["parts"] and "implant" not in c["parts"]
        verified = planned["placement"]["verification"]["clearance_exact_min"]
        assert c["clearance_m"][0] >= verified - 0.0003, site.label
        assert c["depth_m"][-1] == pytest.approx(site.plan.depth)
        assert 0.0 <= c["free_to_depth_m"] <= site.plan.depth


@pytest.mark.parametrize("flags, field", [
    (["--runs", "0"], "--runs"),
    (["--sources", "registration,gravity"], "--sources"),
    (["--sources", "head,head"], "--sources"),
    (["--sensitivity-runs", "-1"], "--sensitivity-runs"),
    (["--approach-mm", "-5"], "--approach-mm"),
    (["--approach-mm", "far"], "--approach-mm"),
    (["--workers", "0"], "--workers"),
    (["--plan", "/nonexistent/plan"], "--plan"),
])
def test_bad_flags_exit_2_naming_the_flag_before_planning(flags, field, tmp_path, monkeypatch):
    def no_planning(**kw):
        raise AssertionError("planned before checking the flags")

    monkeypatch.setattr(A, "sites_of", no_planning)
    code, printed = run_cli(["analyze", "accuracy", *flags, "--out", str(tmp_path / "o")])
    assert code == 2, printed
    assert field in printed and "Traceback" not in printed
    assert not (tmp_path / "o").exists()
