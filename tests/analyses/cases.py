"""Case files the tests write: the bundled default case with its mesh by path, full size or small
(a small FPSM, robot search and capability map: about a second per plan without feeds, the same
stages and checks)."""

from __future__ import annotations

from pathlib import Path

import yaml

from implantplan import models
from implantplan.analyses.case import default_case_path

SMALL = {
    "fpsm": {"slices": 10, "control_points": 10, "samples": 100},
    "robot": {"pop": 12, "gen": 2},
    "capability": {"directions": 20},
}


def default_case_data(*, small: bool = False) -> dict:
    """The bundled default case as a dict, its mesh by path and 100 registration samples (the
    case's 1,000 are the demo's); ``small``: the :data:`SMALL` sizes too."""
    data = yaml.safe_load(default_case_path().read_text())
    data["mesh"]["path"] = str(models.model_path("oral/oralCavityMesh.obj"))
    data["safety"]["registration_samples"] = 100
    if small:
        for section, values in SMALL.items():
            data[section].update(values)
    return data


def write_case(path: Path, data: dict) -> Path:
    path.write_text(yaml.safe_dump(data))
    return path
