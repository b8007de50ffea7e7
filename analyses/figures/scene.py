"""The surgeon's 3D scene of one implant site: a Meshcat static HTML (DESIGN.md section 9).

One scene per site, aimed at the mouth, with everything the plan decided drawn where the plan puts
it, in World (the operating room's floor frame):

- ``/case/scan``: the opened oral scan, semi-transparent (tissue colour);
- ``/case/fpsm/slice_j``: each FPSM slice's closed curve (blue lines);
- ``/case/site``: the implant site (a small sphere) and ``/case/implant_path`` (line2, the path of
  the implant's tip, red);
- ``/case/feeding_target``: the Tool frame's axes (x red, y green, z blue, 10 mm);
- ``/case/fixture``: the virtual fixture's cylinder and cones (a surface of revolution about
  line1, semi-transparent green);
- ``/case/rod``: the handle rod as a capsule of the tool's radius along line1 at the target;
- ``/drake/...``: the Drake plant (the AUBO-i10 with its actuator on the cart, the chair and the
  patient), animated along the straight feed from the pre-feed pose (t = 0) to the target
  (t = 1 s) on the plan's IK branch.

The camera looks at the mouth (Center's origin) from 0.16 m out along the feeding axis and
0.14 m to the side away from the robot; the patient's and chair's collision blobs are hidden
(the scan is the patient here; the Controls menu shows them again), the arm half see-through.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from implantplan.systems.files import write_text_atomic
from implantplan.systems.frames import apply, frame_from_z, invert
from implantplan.systems.robot import kinematics as kin
from implantplan.systems.robot import moprp

TISSUE = (0.90, 0.55, 0.55, 0.55)
FPSM_BLUE = (0.15, 0.35, 0.85, 1.0)
FIXTURE_GREEN = (0.1, 0.75, 0.25, 0.30)
ROD_GREY = (0.55, 0.55, 0.6, 0.9)
IMPLANT_RED = (0.85, 0.1, 0.1, 1.0)
SCENE_PATHS = ("/case/scan", "/case/fpsm", "/case/site", "/case/implant_path",
               "/case/feeding_target", "/case/fixture", "/case/rod")


def _rgba(c):
    from pydrake.geometry import Rgba

    return Rgba(*c)


def _rt(X):
    from pydrake.math import RigidTransform

    return RigidTransform(np.asarray(X, dtype=float))


def revolution_surface(vf, n: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """The fixture's allowed surface (radius R(s) about its axis, from its profile) as a
    triangle mesh in the fixture's frame (Center): (V (k, 3), F (m, 3))."""
    s, r = vf.profile()
    X = frame_from_z(np.zeros(3), vf.direction)
    e1, e2 = X[:3, 0], X[:3, 1]
    t = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    ring = np.cos(t)[:, None] * e1 + np.sin(t)[:, None] * e2  # (n, 3)
    V = (vf.origin + s[:, None, None] * vf.direction + r[:, None, None] * ring[None]).reshape(-1, 3)
    i = np.arange(len(s) - 1)[:, None] * n
    j = np.arange(n)[None, :]
    a, b = i + j, i + (j + 1) % n
    c, d = a + n, b + n
    F = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3),
                        np.stack([a, d, c], -1).reshape(-1, 3)])
    return V, F


def write_site_scene(path: Path, *, fit, placement, robot, site_index: int, feed_samples: int = 30
                     ) -> Path:
    """Write the static HTML of one site's scene (see the module docstring) and return its path.

    Args:
        fit: the pipeline's FitResult (opened scan, FPSM with X_WC = Center in the mesh frame).
        placement: the site's :class:`systems.placement.planner.Placement`.
        robot: the pipeline's RobotResult (scenario, base, branches, X_OT).
        site_index: the site's index in the plan.
    """
    from pydrake.geometry import Meshcat, MeshcatParams

    from implantplan.analyses.figures.robot import record_feed
    from implantplan.diagrams.plant import build_plant

    sc = robot.scenario
    k = site_index
    X_WCenter = sc.X_WO @ robot.X_OC
    meshcat = Meshcat(MeshcatParams(port=0))
    try:
        diagram, plant, _, handles = build_plant(scenario=sc, tool=True, X_WBase=robot.X_WBase,
                                                 limits=sc.limits, meshcat=meshcat)
        draw_site(meshcat, opened=fit.opened, fpsm=fit.fpsm, X_WCenter=X_WCenter,
                  placement=placement)
        u = np.asarray(placement.line2["direction"])
        # the arm along the feed of this site
        feed = moprp.feed_poses(robot.base_xyz, sc.feed_length, feed_samples, X_OT=robot.X_OT[k])
        record_feed(diagram, plant, handles,
                    kin.ik(feed, limits=sc.limits, X_FT=sc.X_FT).q[:, int(robot.branch[k])])
        # the patient's and chair's collision blobs would hide the mouth (the scan shows it):
        # hidden (a toggle in the Controls), the arm half see-through
        meshcat.SetProperty("/drake/visualizer/patient", "visible", False)
        meshcat.SetProperty("/drake/visualizer/aubo", "modulated_opacity", 0.45)
        # camera: out of the mouth along the feeding axis, on the side away from the robot
        target = X_WCenter[:3, 3]
        out_W = X_WCenter[:3, :3] @ u
        away = target - robot.X_WBase[:3, 3]
        away[2] = 0.0
        away /= max(np.linalg.norm(away), 1e-9)
        meshcat.SetCameraPose(target + 0.16 * out_W + 0.14 * away, target)
        write_text_atomic(path, meshcat.StaticHtml())
    finally:
        del meshcat
    return Path(path)


def draw_site(meshcat, *, opened, fpsm, X_WCenter, placement, prefix: str = "/case",
              scan: bool = True, slices: bool | None = None) -> None:
    """Draw one site's case under ``prefix`` (the paths of the module docstring): the scan (when
    ``scan``) and FPSM slices, the site, implant path, feeding target, fixture and rod.

    Args:
        opened: the opened scan (mesh frame); fpsm: the FPSM (its X_WC = Center in the mesh
            frame); X_WCenter: Center in World; placement: anything with the placement's
            X_CH, X_CT, line1, line2 and vf (systems.placement.planner.Placement).
        slices: draw the FPSM slices (None: with the scan).
    """
    from pydrake.geometry import Capsule, Sphere

    X_W_mesh = X_WCenter @ invert(fpsm.X_WC)
    if scan:
        # the scan, in World
        V = apply(X_W_mesh, np.asarray(opened.vertices))
        meshcat.SetTriangleMesh(f"{prefix}/scan", V.T, np.asarray(opened.faces).T,
                                _rgba(TISSUE))
    if (scan if slices is None else slices):
        # FPSM slices
        theta = np.linspace(0.0, 2 * np.pi, 121)
        for j, z in enumerate(fpsm.slice_z):
            rho = fpsm.radius_at(theta, np.full_like(theta, z))
            P = np.stack([rho * np.cos(theta), rho * np.sin(theta), np.full_like(theta, z)], -1)
            meshcat.SetLine(f"{prefix}/fpsm/slice_{j}", apply(X_WCenter, P).T, 2.0,
                            _rgba(FPSM_BLUE))
    # site, implant path, feeding target
    hole_W = apply(X_WCenter, placement.X_CH[:3, 3])
    meshcat.SetObject(f"{prefix}/site", Sphere(0.0015), _rgba(IMPLANT_RED))
    meshcat.SetTransform(f"{prefix}/site", _rt(frame_from_z(hole_W, [0.0, 0.0, 1.0])))
    l1, l2 = placement.line1, placement.line2
    u = np.asarray(l2["direction"])
    start2 = np.asarray(l2["start"])
    meshcat.SetLine(f"{prefix}/implant_path",
                    apply(X_WCenter, np.stack([start2, placement.X_CH[:3, 3]])).T, 4.0,
                    _rgba(IMPLANT_RED))
    X_WT = X_WCenter @ placement.X_CT
    for axis, color in enumerate(((1, 0, 0, 1), (0, 0.7, 0, 1), (0, 0, 1, 1))):
        ends = np.stack([X_WT[:3, 3], X_WT[:3, 3] + 0.01 * X_WT[:3, axis]])
        meshcat.SetLine(f"{prefix}/feeding_target/{'xyz'[axis]}", ends.T, 3.0, _rgba(color))
    # the fixture and the rod at the target
    Vf, Ff = revolution_surface(placement.vf)
    meshcat.SetTriangleMesh(f"{prefix}/fixture", apply(X_WCenter, Vf).T, Ff.T,
                            _rgba(FIXTURE_GREEN))
    r = float(l1["radius"])
    rod_len = float(placement.vf.profile()[0][-1])
    mid = np.asarray(l1["start"]) + 0.5 * rod_len * u
    X_C_rod = frame_from_z(mid, u)
    meshcat.SetObject(f"{prefix}/rod", Capsule(max(r, 1e-4), rod_len), _rgba(ROD_GREY))
    meshcat.SetTransform(f"{prefix}/rod", _rt(X_WCenter @ X_C_rod))
