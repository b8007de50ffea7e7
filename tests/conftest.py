"""Fixtures shared by several test files."""

import contextlib
import io
import os

import pytest
from hypothesis import settings

from implantplan.analyses.cli import main

# CI runs the property tests derandomized (the same examples every run: a red CI is then always
# reproducible); locally they explore new examples each run.
settings.register_profile("ci", derandomize=True, print_blob=True)
if os.environ.get("CI"):
    settings.load_profile("ci")


@pytest.fixture(scope="session")
def demo_run(tmp_path_factory):
    """``implantplan demo`` once, as the README's first command runs it (the case's feeds, the 3D
    scenes): ``(plan folder, everything it printed)``."""
    out = tmp_path_factory.mktemp("demo") / "plan"
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed), contextlib.redirect_stderr(printed):
        code = main(["demo", "--out", str(out)])
    assert code == 0, printed.getvalue()
    return out, printed.getvalue()


@pytest.fixture(scope="session")
def demo_plan(demo_run):
    """The bundled default case planned once (the plan folder of :func:`demo_run`)."""
    return demo_run[0]
