"""The region check study: the plan's certified region against FCL at random region poses."""

import pytest

from implantplan.analyses.studies import region_check


def test_a_bad_sample_count_exits_2_naming_the_flag(capsys):
    assert region_check.main(["--samples", "0"]) == 2
    assert "--samples" in capsys.readouterr().err


@pytest.mark.sweep
def test_the_default_plan_has_no_false_safe_region_sample(capsys):
    """The bundled default case: each site's certified value is at most FCL's minimum over
    2,000 uniform random poses of its fixture region (exit 0), and within 0.5 mm of it."""
    assert region_check.main(["--samples", "2000"]) == 0
    out = capsys.readouterr().out
    res = region_check.study([region_check_default()], samples=500, seed=1)
    for r in res["sites"].values():
        assert r["false_safe"] == 0 and 0 <= r["gap_m"] < 0.5e-3, r
    assert out.count("false-safe 0") == 2


def region_check_default():
    from implantplan.analyses.case import default_case_path

    return default_case_path()
