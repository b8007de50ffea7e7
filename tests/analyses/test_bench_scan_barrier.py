"""The scan-barrier benchmark on the default plan: every bound row, none false-safe."""

from implantplan.analyses import bench_scan_barrier


def test_the_bench_compares_the_bounds_on_the_default_plan(demo_plan, capsys):
    assert bench_scan_barrier.main(["--plan", str(demo_plan)]) == 0
    rows = [line.split() for line in capsys.readouterr().out.splitlines()[1:]]
    bounds = [r for r in rows if r[1] in ("FPSM", "scan,")]
    assert len(bounds) == 2 * (1 + len(bench_scan_barrier.CAPS))  # two sites
    for r in bounds:
        false_safe = int(r[-2])
        assert false_safe == 0, r


def test_a_missing_plan_exits_2(tmp_path, capsys):
    assert bench_scan_barrier.main(["--plan", str(tmp_path / "nothing")]) == 2
    assert "--plan" in capsys.readouterr().err
