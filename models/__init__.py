"""Model files shipped with implantplan, and where to find them.

Drake resolves ``package://implantplan/...`` through ``package.xml`` in this folder; use
:func:`add_package` on a parser's package map so nothing is downloaded at run time.
"""

from __future__ import annotations

from pathlib import Path

MODELS_DIR = Path(__file__).resolve().parent
PACKAGE_XML = MODELS_DIR / "package.xml"


def add_package(package_map) -> None:
    """Register the ``implantplan`` package with a Drake ``PackageMap`` (idempotent)."""
    if not package_map.Contains("implantplan"):
        package_map.AddPackageXml(str(PACKAGE_XML))


def model_path(relative: str) -> Path:
    """Absolute path of a model file given relative to ``models/``; raises if it is missing."""
    path = MODELS_DIR / relative
    if not path.exists():
        raise FileNotFoundError(f"model file {relative!r} not found under {MODELS_DIR}")
    return path
