"""Fixtures shared by several test files."""

import pytest

from analyses.cli import main


@pytest.fixture(scope="session")
def demo_plan(tmp_path_factory):
    """The bundled default case planned once (one feed per site, with the 3D scene)."""
    out = tmp_path_factory.mktemp("demo") / "plan"
    assert main(["demo", "--out", str(out), "--runs", "1", "--quiet"]) == 0
    return out
