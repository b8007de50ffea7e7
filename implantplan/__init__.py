"""implantplan: planning and teleoperation simulation for robot-assisted dental implant surgery.

One import package: the folders ``systems/``, ``diagrams/``, ``analyses/`` and ``models/`` at the
repository root install as ``implantplan.systems``, ``implantplan.diagrams``,
``implantplan.analyses`` and ``implantplan.models`` (DESIGN.md section 2). Layers import downward
only: models <- systems <- diagrams <- analyses.
"""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("implantplan")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0+unknown"
