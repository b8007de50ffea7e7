"""The awake patient on the command line: simulate feeding --head-motion, analyze head-motion."""

import json

import pytest

from implantplan.analyses.cli import main


def test_feeding_with_head_motion_writes_the_profile(tmp_path, capsys):
    out = tmp_path / "feed"
    code = main(["simulate", "feeding", "--runs", "1", "--head-motion", "breathing", "--seed",
                 "2", "--out", str(out), "--quiet"])
    assert code == 0, capsys.readouterr()
    data = json.loads((out / "feeding.json").read_text())
    assert data["head_motion"]["profile"] == "breathing" and data["head_motion"]["seed"] == 2
    run = data["runs"][0]
    assert run["reached_target"] and not run["head_guard_stopped"]
    assert 0 < run["max_margin_extra"] < 0.003


def test_bad_head_motion_is_a_user_error(tmp_path, capsys):
    code = main(["simulate", "feeding", "--runs", "1", "--head-motion", "sneeze", "--out",
                 str(tmp_path / "x"), "--quiet"])
    assert code == 2
    assert "--head-motion" in capsys.readouterr().err
    code = main(["simulate", "feeding", "--runs", "1", "--head-motion", str(tmp_path / "no.csv"),
                 "--out", str(tmp_path / "y"), "--quiet"])
    assert code == 2
    assert "--head-motion" in capsys.readouterr().err


def test_head_motion_study_small(tmp_path, capsys):
    out = tmp_path / "study"
    code = main(["analyze", "head-motion", "--runs", "1", "--profiles", "startle", "--case",
                 "cylinder", "--out", str(out), "--quiet"])
    assert code == 0, capsys.readouterr()
    data = json.loads((out / "head_motion.json").read_text())
    s = data["profiles"]["startle"]["summary"]
    assert s["runs"] == 1 and s["runs_below_zero_following"] == 0
    assert data["lost_tracking"]["trigger_cause"] == 1
    assert (out / "head_startle.png").is_file()
    assert "startle: 1 runs" in capsys.readouterr().out


@pytest.mark.sweep
def test_head_motion_study_on_the_scan(demo_plan, tmp_path, capsys):
    """The bundled default case's plan folder: every site, FCL against the moving opened
    scan (the default run has the study's small version; the studies' cores on the scan are
    tested in tests/diagrams/test_teleop_head.py)."""
    out = tmp_path / "scan"
    code = main(["analyze", "head-motion", "--runs", "1", "--profiles", "breathing",
                 "--plan", str(demo_plan), "--out", str(out), "--quiet"])
    assert code == 0, capsys.readouterr()
    data = json.loads((out / "head_motion.json").read_text())
    assert data["case"] == "scan" and len(data["sites"]) == 2
    assert data["plan"] == str(demo_plan)
    for label, site in data["sites"].items():
        s = site["profiles"]["breathing"]["summary"]
        assert s["runs"] == 1 and s["runs_below_zero_following"] == 0
        # the scan is near: a few mm, not the cylinder's 30 mm
        assert 0.0 < s["exact_clearance_min_following"] < 0.01
        assert (out / label / "head_breathing.png").is_file()
    # the study's report: a table per site and its figures
    page = (out / "report.html").read_text()
    assert data["passed"] is True and data["tracker"]["predict_samples"] == 2
    for label in data["sites"]:
        assert f"<h2>{label}</h2>" in page and f"{label}/head_breathing.png" in page
    assert "deviation following" in page


@pytest.mark.sweep
def test_a_feed_held_through_a_swallow_waits_and_reaches_the_target(demo_plan):
    """Site 36, swallow, run 35 of 50 (seed 0): the swallow grows the guard's margin past the
    clearance at the narrowest part of the feed, the barrier holds the tool there for about a
    second (no guard stop), and the operator's script plus its 2 s finish ends 8.5 mm short;
    the study runs it again with the longer finish and the feed reaches the target, clear."""
    from implantplan.analyses.studies import head_motion as S
    from implantplan.diagrams import feeding as F
    from implantplan.diagrams.teleop import build_teleop, simulate
    from implantplan.systems import seeds
    from implantplan.systems.teleop.head_motion import HeadMotion, neck_of
    from implantplan.systems.teleop.master_device import feeding_runs
    from implantplan.systems.teleop.tracker import TrackerParams

    case, cavity = S.scan_cases(plan=demo_plan)[0]
    i = 35
    m = feeding_runs(case.X_WE(case.q_start)[:3, 3], case.X_WTarget[:3, 3], runs=50, seed=0)[i]
    hm = HeadMotion.make("swallow", seed=seeds.seed(0, i, 0), pivot=case.X_WCenter[:3, 3],
                         neck=neck_of(case.X_WCenter))
    trk = TrackerParams(seed=seeds.seed(0, i, 1))
    still_teleop = build_teleop(case)
    still = simulate(still_teleop, m.duration + F.FINISH_SECONDS, motion=m)
    run, fig, still_long = S.following_run(case, m, hm, trk, cavity, still=still,
                                           still_teleop=still_teleop)
    assert fig["waited"] and fig["reached_target"] and fig["trigger_time"] < 0
    assert run.sim_seconds == pytest.approx(m.duration + F.FINISH_SECONDS + S.WAIT_SECONDS)
    assert len(still_long.t) == len(run.t)
    assert fig["exact_clearance_min"] >= 1e-3  # the margin, on the opened scan (FCL)


def test_tracker_flags_are_checked_and_named(tmp_path, capsys):
    for flags, name in ((["--tracker-rate-hz", "90"], "--tracker-rate-hz"),
                        (["--tracker-latency-ms", "-5"], "--tracker-latency-ms"),
                        (["--prediction-samples", "1"], "--prediction-samples")):
        code = main(["analyze", "head-motion", "--runs", "1", "--case", "cylinder", *flags,
                     "--out", str(tmp_path / "x"), "--quiet"])
        assert code == 2
        assert name in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_study_flags_are_checked_before_any_planning(tmp_path, capsys, monkeypatch):
    """A bad flag of the scan study is exit 2 naming it, before the default case is planned."""
    from implantplan.analyses.studies import scan_reference

    def no_planning(**kwargs):
        raise AssertionError("planned the default case before checking the flags")

    monkeypatch.setattr(scan_reference, "default_case_sites", no_planning)
    for flags, name in ((["--profiles", "sneeze"], "--profiles"),
                        (["--profiles", ","], "--profiles"),
                        (["--runs", "0"], "--runs"),
                        (["--tracker-latency-ms", "500"], "--tracker-latency-ms"),
                        (["--case", "cylinder", "--plan", str(tmp_path)], "--plan"),
                        (["--plan", str(tmp_path / "nowhere")], "--plan")):
        code = main(["analyze", "head-motion", *flags, "--out", str(tmp_path / "x"), "--quiet"])
        assert code == 2, flags
        err = capsys.readouterr().err
        assert name in err and "Traceback" not in err, err
    assert not (tmp_path / "x").exists()


def test_a_plan_without_its_case_file_is_exit_2_naming_plan(demo_plan, tmp_path, capsys):
    """The exact reference is the plan's case's scan: a plan whose case file is gone cannot be
    studied, and says so."""
    import shutil

    plan = shutil.copytree(demo_plan, tmp_path / "plan")
    data = json.loads((plan / "plan.json").read_text())
    data["case"]["source"] = str(tmp_path / "gone.yaml")
    (plan / "plan.json").write_text(json.dumps(data))
    code = main(["analyze", "head-motion", "--runs", "1", "--profiles", "breathing",
                 "--plan", str(plan), "--out", str(tmp_path / "x"), "--quiet"])
    assert code == 2
    err = capsys.readouterr().err
    assert "--plan" in err and "gone.yaml" in err and "is not there" in err
    assert not (tmp_path / "x").exists()
