"""The exact reference of the teleop studies on the bundled default case (the adversarial
operator, analyses.adversarial; the awake patient, analyses.head_study): the case planned as
``implantplan plan`` does, and FCL (python-fcl) between the whole tool and the opened scan.

The tool is systems.tool_clearance's :class:`ToolGeometry` (the body the barrier bounds): each
capsule's clearance is its axis's FCL distance to the scan minus its radius (exact while the
axis is free), and minus its radius where the axis itself touches the scan (at or below the
true value). FCL's contact depths of a capsule in a mesh are not used: zero or denormal depths
were seen for real contacts, which made a 0.61 mm contact read as 0.
"""

from __future__ import annotations

import fcl
import numpy as np

from implantplan.analyses import pipeline
from implantplan.analyses.case import default_case_path, load_case
from implantplan.diagrams.teleop import TeleopCase
from implantplan.systems.frames import frame_from_z, transform
from implantplan.systems.tool_clearance import ToolGeometry

IMPLANT_AXIS_RADIUS = 1e-4  # m: the implant as its axis (a thin capsule for FCL)


class ExactClearance:
    """FCL distance of the tool's capsules to a triangle mesh (both in the mesh frame, m).

    The tool is systems.tool_clearance's :class:`ToolGeometry` (the body the barrier bounds):
    each of its capsules (segment a-b in Tool, radius r) as an FCL capsule, a sphere where the
    segment is a point; a radius-0 segment (the implant's axis) gets ``IMPLANT_AXIS_RADIUS``.
    """

    def __init__(self, vertices, faces, tool: ToolGeometry):
        model = fcl.BVHModel()
        model.beginModel(len(vertices), len(faces))
        model.addSubModel(np.asarray(vertices, dtype=float), np.asarray(faces, dtype=np.int64))
        model.endModel()
        self._mesh = fcl.CollisionObject(model, fcl.Transform())
        self._parts = []  # (the part's axis as a zero-radius shape, X_T_axis, radius)
        for a, b, r in zip(*tool.capsules_T(), strict=True):
            r = max(float(r), IMPLANT_AXIS_RADIUS)
            length = float(np.linalg.norm(b - a))
            if length < 1e-12:
                self._parts.append((fcl.Sphere(0.0), transform(np.eye(3), a), r))
            else:  # fcl capsules lie along their local z, centred
                self._parts.append((fcl.Capsule(0.0, length), frame_from_z((a + b) / 2, b - a), r))

    def __call__(self, X_MT: np.ndarray) -> np.ndarray:
        """(K,) clearance (m) of the tool at poses X_MT (K, 4, 4) of its Tool frame in the mesh
        frame: the smallest over its parts of (the axis's FCL distance to the mesh - r), exact
        for a part whose axis is free; -r where the axis itself touches the mesh (collide), a
        value at or below the true one (FCL's contact depths of a capsule in a mesh are not
        reliable: zero or denormal depths were seen for real contacts)."""
        out = np.empty(X_MT.shape[0])
        dreq = fcl.DistanceRequest()
        creq = fcl.CollisionRequest()
        for k, X in enumerate(np.asarray(X_MT, dtype=float)):
            best = np.inf
            for shape, X_TS, r in self._parts:
                X_MS = X @ X_TS
                obj = fcl.CollisionObject(shape, fcl.Transform(X_MS[:3, :3], X_MS[:3, 3]))
                if fcl.collide(obj, self._mesh, creq, fcl.CollisionResult()) > 0:
                    d = -r
                else:
                    d = max(float(fcl.distance(obj, self._mesh, dreq, fcl.DistanceResult())),
                            0.0) - r
                best = min(best, d)
            out[k] = best
        return out


def default_case_sites(*, progress=None):
    """(teleop cases per site, the opened scan mesh) of the bundled default case, planned as
    ``implantplan plan`` does."""
    case = load_case(default_case_path())
    fit = pipeline.fit_stage(case)
    placements = pipeline.placement_stage(case, fit.fpsm)
    robot = pipeline.robot_stage(case, placements)
    return pipeline.teleop_cases(case, fit, placements, robot), fit.opened


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
