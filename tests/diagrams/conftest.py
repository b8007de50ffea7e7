"""Fixtures of the diagrams tests: seed 000's cylinder check placed once per session and its
feeding case at the knee layout of the lying scenario (the tests read them, never change
them)."""

import pytest

from implantplan.diagrams import feeding as F


@pytest.fixture(scope="session")
def cylinder_instrument():
    """diagrams.feeding.default_instrument(): seed 000's cylinder check, placed by PSO."""
    return F.default_instrument()


@pytest.fixture(scope="session")
def knee_case(cylinder_instrument):
    """The cylinder instrument's feeding case in the lying scenario at the knee point of 100
    random feasible bases."""
    sc, sc_plant = F.load_scenario("lying")
    xyz, branch, _ = F.knee_layout(sc, seed=0, candidates=100)
    return F.make_case("lying", sc_plant, xyz, branch, cylinder_instrument)
