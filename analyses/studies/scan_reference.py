"""The exact reference of the teleop studies on the bundled default case (the adversarial
operator, analyses.studies.adversarial; the awake patient, analyses.studies.head_motion): the case
planned as
``implantplan plan`` does, and FCL (python-fcl) between the whole tool and the opened scan.

The instrument is the teleop case's :class:`systems.instrument.Instrument` (the body the
barrier bounds), each solid as it is: a capsule's clearance is its axis's FCL distance to the scan
minus its radius (exact while the axis is free), minus its radius where the axis itself touches
the scan (at or below the true value); a cylinder's is FCL's cylinder-to-mesh distance while it
is free. FCL's contact depths in a mesh are not used: zero or denormal depths were seen for real
contacts, which made a 0.61 mm contact read as 0.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import trimesh

from implantplan.analyses import pipeline
from implantplan.analyses.case import default_case_path, load_case
from implantplan.diagrams.teleop import TeleopCase
from implantplan.systems.errors import InputError
from implantplan.systems.instrument import Instrument
from implantplan.systems.placement.exact_clearance import ExactCavity

IMPLANT_AXIS_RADIUS = 1e-4  # m: the implant as its axis (a thin capsule for FCL)


class ExactClearance:
    """FCL clearance of the whole instrument to a triangle mesh (both in the mesh frame, m):
    :meth:`systems.placement.exact_clearance.ExactCavity.tool_clearance` (every solid as it is),
    the implant's radius-0 axis of the paper tool as a capsule of ``IMPLANT_AXIS_RADIUS``. No
    start-in-tissue test: the opened scan is not the Center-axis star-shaped cavity that test
    assumes.
    """

    def __init__(self, vertices, faces, tool: Instrument):
        mesh = trimesh.Trimesh(np.asarray(vertices, dtype=float), np.asarray(faces), process=False)
        self._cavity = ExactCavity(mesh)
        self._tool = thickened(tool, IMPLANT_AXIS_RADIUS)

    def __call__(self, X_MT: np.ndarray) -> np.ndarray:
        """(K,) clearance (m) of the instrument at poses X_MT (K, 4, 4) of its Tool frame in the
        mesh frame: the smallest over its solids; exact while a solid is free, at or below the
        true value where it touches (FCL's contact depths in a mesh are not used: zero or
        denormal depths were seen for real contacts)."""
        return self._cavity.tool_clearance(np.asarray(X_MT, dtype=float).reshape(-1, 4, 4),
                                           self._tool, check_start=False)


def thickened(tool: Instrument, radius: float) -> Instrument:
    """The instrument with every solid at least ``radius`` thick (a radius-0 axis becomes a
    thin capsule FCL can measure)."""
    shapes = tuple(dataclasses.replace(s, radius=max(s.radius, radius)) for s in tool.shapes)
    return dataclasses.replace(tool, shapes=shapes)


def default_case_sites(*, progress=None):
    """(teleop cases per site, the opened scan mesh) of the bundled default case, planned as
    ``implantplan plan`` does."""
    case = load_case(default_case_path())
    fit = pipeline.fit_stage(case)
    placements = pipeline.placement_stage(case, fit.fpsm)
    robot = pipeline.robot_stage(case, placements)
    return pipeline.teleop_cases(case, fit, placements, robot), fit.opened


def plan_sites(folder, *, field: str = "--plan"):
    """(teleop cases per site, the opened scan mesh) of a plan folder (``implantplan plan`` or
    ``demo``): the sites, fixtures and layout as planned, the scan of the case file the plan
    names; errors name ``field``."""
    from implantplan.analyses.live_setup import load_plan, opened_scan

    sp = load_plan(folder, field=field, reference=False)
    mesh = opened_scan(sp)
    if mesh is None:
        raise InputError(field, f"{sp.folder}: the case file the plan names "
                         f"({sp.plan['case']['source']}) is not there; the exact reference "
                         "needs its scan")
    return [sp.teleop_case(k) for k in range(len(sp.names))], mesh


def exact_for(tc: TeleopCase, mesh) -> ExactClearance:
    """The exact reference for a site: the opened scan without the tissue in front of the
    mouth opening (faces with a vertex beyond the FPSM's top slice plane: the lips and cheeks
    there are retracted in surgery, the case's own assumption), the tool of ``tc``."""
    V = np.asarray(mesh.vertices, dtype=float)
    X_CM = np.linalg.inv(tc.fpsm.X_WC)  # mesh frame -> Center
    z = V @ X_CM[2, :3] + X_CM[2, 3]
    faces = np.asarray(mesh.faces)
    keep = np.all(z[faces] <= tc.fpsm.z_range[1], axis=1)
    return ExactClearance(V, faces[keep], tc.tool)
