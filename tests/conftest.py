"""Fixtures shared by several test files.

The bundled default case is planned once per test run (:func:`demo_run`): under pytest-xdist
each worker process has its own session, so the first worker that asks plans it into the folder
the workers share (``tmp_path_factory.getbasetemp().parent``) under a file lock, and the others
read that folder. Tests read the plan folder; a test that writes into a plan folder copies it
first (:func:`plan_copy` in the studio tests). The default case at its small sizes is planned once
per run the same way (:func:`small_plan`)."""

import contextlib
import io
import os
import sys
from pathlib import Path

# The parallel numba kernels run on OpenMP (libgomp), whose threads spin at every barrier unless
# told to sleep; with one pytest-xdist worker per core, two workers' spinning threads take the
# cores from each other (measured: ~16% of the suite's CPU time). Set before anything loads
# libgomp; the workers and the subprocesses the tests start inherit it; the results are the same.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
# Bytecode is cached even where PYTHONDONTWRITEBYTECODE is set (it is on this machine): without
# it each test worker compiles and assertion-rewrites every test module at collection (measured:
# 7.9 s, 3.6 s with the cache) and every CLI subprocess compiles the project again. __pycache__
# folders are ignored by git; the workers and the subprocesses inherit the variable's removal,
# this process takes ``sys.dont_write_bytecode`` below (before any test module is imported).
os.environ.pop("PYTHONDONTWRITEBYTECODE", None)

import pytest
from hypothesis import settings

from implantplan.analyses.cli import main

sys.dont_write_bytecode = False  # see PYTHONDONTWRITEBYTECODE above

# CI runs the property tests derandomized (the same examples every run: a red CI is then always
# reproducible); locally they explore new examples each run.
settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")


def run_cli(argv: list[str]) -> tuple[int, str]:
    """``implantplan ARGV`` in this process: (exit code, everything it printed)."""
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed), contextlib.redirect_stderr(printed):
        code = main(argv)
    return code, printed.getvalue()


def once_per_run(tmp_path_factory, name: str, make) -> Path:
    """The folder ``name`` made by ``make(folder)`` once per test run: in this session's temp
    folder without xdist; with xdist in the folder all workers share, the first worker making it
    under a lock while the others wait, then read it. ``make`` writes the folder whole or raises
    (a failure leaves no folder, so the next worker tries again and fails the same way)."""
    if os.environ.get("PYTEST_XDIST_WORKER") is None:
        folder = tmp_path_factory.mktemp(name)
        make(folder)
        return folder
    from filelock import FileLock

    root = tmp_path_factory.getbasetemp().parent
    folder, done = root / name, root / f"{name}.done"
    with FileLock(str(root / f"{name}.lock")):
        if not done.is_file():
            import shutil

            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
            make(folder)
            done.write_text("made\n")
    return folder


def _plan_demo(folder: Path) -> None:
    code, printed = run_cli(["demo", "--out", str(folder / "plan")])
    assert code == 0, printed
    (folder / "printed.txt").write_text(printed, encoding="utf-8")


@pytest.fixture(scope="session")
def demo_run(tmp_path_factory):
    """``implantplan demo`` once per test run, as the README's first command runs it (the case's
    feeds, the 3D scenes): ``(plan folder, everything it printed)``."""
    folder = once_per_run(tmp_path_factory, "demo", _plan_demo)
    return folder / "plan", (folder / "printed.txt").read_text(encoding="utf-8")


@pytest.fixture(scope="session")
def demo_plan(demo_run):
    """The bundled default case planned once (the plan folder of :func:`demo_run`); read it, or
    copy it before writing into it."""
    return demo_run[0]


# the flags of :func:`small_plan`'s run: one feed per site, no figures
SMALL_PLAN_FLAGS = ["--runs", "1", "--no-figures", "--quiet"]


def _plan_small(folder: Path) -> None:
    from tests.analyses.cases import default_case_data, write_case

    data = default_case_data(small=True)
    data["safety"]["registration_samples"] = 20
    case = write_case(folder / "case.yaml", data)
    code, printed = run_cli(["plan", str(case), "--out", str(folder / "plan"),
                             *SMALL_PLAN_FLAGS])
    assert code == 0, printed


@pytest.fixture(scope="session")
def small_plan(tmp_path_factory):
    """The default case at its small sizes (tests.analyses.cases.SMALL, 20 registration samples)
    planned once per test run with :data:`SMALL_PLAN_FLAGS`: ``(case file, plan folder)``. Read
    them (plan the case file again for a second plan), or copy the folder before writing into
    it."""
    folder = once_per_run(tmp_path_factory, "small", _plan_small)
    return folder / "case.yaml", folder / "plan"


def _file_rank(item) -> int:
    """The order the files run in: the file whose first test plans the default case, then the
    files that need no plan (systems, diagrams, layers), then the other command tests. Under
    pytest-xdist (each file on one worker, handed out in this order) one worker plans while the
    other runs the cores, so no worker waits on the plan's lock."""
    path = Path(str(item.fspath))
    if path.name == "test_plan.py":
        return 0
    return 2 if path.parent.name == "analyses" else 1


def pytest_collection_modifyitems(config, items):
    items.sort(key=_file_rank)  # stable: the order inside each file and rank is kept
