"""The exact reference of the teleop studies on the bundled default case (the adversarial
operator, analyses.studies.adversarial; the awake patient, analyses.studies.head_motion): the case
planned as
``implantplan plan`` does, and FCL (python-fcl) between the whole tool and the opened scan.

The tool is systems.placement.tool_clearance's :class:`ToolGeometry` (the body the barrier bounds):
each
capsule's clearance is its axis's FCL distance to the scan minus its radius (exact while the
axis is free), and minus its radius where the axis itself touches the scan (at or below the
true value). FCL's contact depths of a capsule in a mesh are not used: zero or denormal depths
were seen for real contacts, which made a 0.61 mm contact read as 0.
"""

from __future__ import annotations

import numpy as np
import trimesh

from implantplan.analyses import pipeline
from implantplan.analyses.case import default_case_path, load_case
from implantplan.diagrams.teleop import TeleopCase
from implantplan.systems.errors import InputError
from implantplan.systems.placement.exact_clearance import ExactCavity
from implantplan.systems.placement.tool_clearance import ToolGeometry, tool_capsules

IMPLANT_AXIS_RADIUS = 1e-4  # m: the implant as its axis (a thin capsule for FCL)


class ExactClearance:
    """FCL clearance of the tool's capsules to a triangle mesh (both in the mesh frame, m):
    systems.placement.exact_clearance.ExactCavity's capsule clearance (the axis's distance minus r,
    -r
    where the axis touches), each capsule of :class:`ToolGeometry` with a radius of at least
    ``IMPLANT_AXIS_RADIUS`` (the implant's radius-0 axis as a thin capsule). No start-in-tissue
    test: the opened scan is not the Center-axis star-shaped cavity that test assumes.
    """

    def __init__(self, vertices, faces, tool: ToolGeometry):
        mesh = trimesh.Trimesh(np.asarray(vertices, dtype=float), np.asarray(faces), process=False)
        self._cavity = ExactCavity(mesh)
        self._tool = tool
        self._r = np.maximum(tool.capsules_T()[2], IMPLANT_AXIS_RADIUS)

    def __call__(self, X_MT: np.ndarray) -> np.ndarray:
        """(K,) clearance (m) of the tool at poses X_MT (K, 4, 4) of its Tool frame in the mesh
        frame: the smallest over its capsules; exact while a capsule's axis is free, at or
        below the true value where it touches (FCL's contact depths of a capsule in a mesh are
        not used: zero or denormal depths were seen for real contacts)."""
        X = np.asarray(X_MT, dtype=float).reshape(-1, 4, 4)
        A, B, _ = tool_capsules(X, self._tool)
        n, C = A.shape[:2]
        c = self._cavity.capsule_clearance(A.reshape(-1, 3), B.reshape(-1, 3),
                                           np.tile(self._r, n), check_start=False)
        return c.reshape(n, C).min(axis=1)


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
