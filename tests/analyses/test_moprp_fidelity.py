"""The MOPRP fidelity study's pieces (analyses.studies.moprp_fidelity)."""

import numpy as np
import pytest

from implantplan.analyses.cli import main
from implantplan.analyses.studies import moprp_fidelity as mf
from implantplan.diagrams import plant as scene
from implantplan.systems import actuator
from implantplan.systems.robot import moprp


@pytest.fixture(scope="module")
def layout():
    sc = moprp.load_scenario("lying", X_FT=actuator.X_FT())
    xyz = np.array(scene.DEFAULT_BASE_XYZ["lying"])
    ev = moprp.evaluate_bases(xyz[None], sc, np.random.default_rng(0))
    return sc, xyz, int(ev.branch[0]), ev


def test_ideal_operator_travel_is_the_joint_variation_index(layout):
    """With no tremor, drift, pause or overshoot the operator's TCP runs the straight feed, so
    its joint travel is the index I_j (sampled at 11 poses; the path is the same)."""
    sc, xyz, b, ev = layout
    ideal = mf.operator_travel(xyz, b, sc, mf.OPERATORS["ideal"], feeds=1)
    assert ideal == pytest.approx(ev.objectives[0, 2], rel=1e-3)
    tremor = mf.operator_travel(xyz, b, sc, mf.OPERATORS["tremor only"], feeds=1)
    assert tremor > ideal  # the 9 Hz tremor adds joint travel


def test_gii_units(layout):
    sc, xyz, b, _ = layout
    g = mf.gii_units(xyz, b, sc, np.random.default_rng(0))
    ref = moprp.gii(xyz, b, sc, np.random.default_rng(0))["gii"]
    assert g["SI"] == pytest.approx(ref, rel=1e-12)
    assert 0 < g["SI"] < 1 and 0 < g["mm/deg"] < 1 and 0 < g["J_v"] < 1
    assert g["mm/deg"] != pytest.approx(g["SI"], rel=1e-3)  # units change the GII


def test_rank_and_rules():
    assert mf.rank(2.0, [1.0, 3.0, np.nan], higher_is_better=False) == 2
    assert mf.rank(2.0, [1.0, 3.0, 2.0], higher_is_better=True) == 2  # ties in its favour
    F = np.array([[1.0, 0.001, 1.0], [2.0, 0.0005, 0.5], [1.5, 0.002, 0.1]])
    rng = np.random.default_rng(0)
    assert mf.select(F, "joint variation only", rng) == 2
    assert mf.select(F, "raw sum SI", rng) == 2
    assert mf.select(F, "raw sum mm/deg", rng) == 2  # 1 + 1 + 57 vs 2 + 0.5 + 29 vs 1.5 + 2 + 6
    assert mf.select(F, "knee", rng) == moprp.knee_point(F)
    assert mf.select(F, "score", rng) in (0, 1, 2)
    with pytest.raises(Exception, match="rule"):
        mf.select(F, "nope", rng)


def test_cli_rejects_bad_counts(tmp_path, capsys):
    code = main(["analyze", "moprp-fidelity", "--draws", "0", "--out", str(tmp_path)])
    assert code == 2 and "--draws" in capsys.readouterr().err
