"""Fixtures shared by several test files."""

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
def demo_plan(tmp_path_factory):
    """The bundled default case planned once (one feed per site, with the 3D scene)."""
    out = tmp_path_factory.mktemp("demo") / "plan"
    assert main(["demo", "--out", str(out), "--runs", "1", "--quiet"]) == 0
    return out
