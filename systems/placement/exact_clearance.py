"""Exact tool clearance against the scan mesh with FCL: the ground truth.

The fast safety models (the FPSM's :mod:`systems.placement.tool_clearance`, the scan bound of
:mod:`systems.placement.scan_clearance`) certify clearance; this module answers the same
questions against the triangle mesh itself, with an OBB-RSS BVH of the mesh and capsule,
cylinder and sphere collision and distance queries. The tests use it as ground truth and the
plan's final checks verify the planned instrument with it.

**Which FCL.** Coal (the maintained successor of FCL, formerly hpp-fcl), with GJK stopped on an
absolute duality gap of ``GJK_GAP`` (1e-12 m^2 on the squared distance): the distance it returns
is that of two points of the solids, proven close to the true one. python-fcl's (libccd) GJK
stops on a relative tolerance and was measured 0.05 mm above the true distance of the actuator's
head cylinder near the margin (1.0014 mm where points of the head are 0.9484 mm from the scan),
on the unsafe side; Coal gives 0.948361 mm there. ``tests/systems/placement/
test_exact_clearance.py`` checks cylinders and capsules on the scan against dense surface
samples' exact point distances (libigl): never above them by more than ``REFERENCE_ERROR``
(1 nm), never below them by more than their spacing. Coarser gaps (1e-9 m^2 measured 0.2 um
high) and finer ones (1e-15: GJK gives up and answers -inf) are worse.

**The mesh as the FPSM sees it.** The scan is taken into the Center frame, its open cuts closed
as the FPSM fit closes them (:func:`systems.fpsm.oral_mesh.close_open_cuts`), and cut at the mouth
opening (the top slice plane z = z_top): above it the lips and cheeks are held back by a
retractor, so nothing there is an obstacle (DESIGN.md section 4; the FPSM leaves it free too).

**Signed clearance of a capsule** (axis p0-p1, radius r) whose start p0 lies in the cavity:
with d the exact distance from the axis segment to the mesh, the clearance is d - r when the
axis does not touch the mesh; when it does, the capsule is at least r deep and the value is -r
(a penetration of at least r; the acceptance counts only the sign and small depths). Whether p0
is in the cavity or in tissue is decided exactly too: the horizontal segment from the Center
axis (0, 0, z_p0) to p0 lies inside the FPSM slice (every slice is star-shaped about the axis),
which lies inside the cavity, so p0 is in tissue exactly when that segment crosses the mesh
(then the value is -r as well).
"""

from __future__ import annotations

import coal
import numpy as np
import trimesh

from implantplan.systems.errors import InputError
from implantplan.systems.frames import invert, rotations
from implantplan.systems.safety import SafetySpec

GJK_GAP = 1e-12  # m^2: GJK stops when the squared distance is proven within this of the true
REFERENCE_ERROR = 1e-9  # m: the most the reference was measured above the true distance


def distance_request() -> coal.DistanceRequest:
    """Coal's distance request of every exact query: GJK stopped on an absolute duality gap of
    ``GJK_GAP`` on the squared distance (module notes), exact BVH traversal (no relative or
    absolute pruning error)."""
    req = coal.DistanceRequest()
    req.gjk_convergence_criterion = coal.GJKConvergenceCriterion.DualityGap
    req.gjk_convergence_criterion_type = coal.GJKConvergenceCriterionType.Absolute
    req.gjk_tolerance = GJK_GAP
    req.gjk_max_iterations = 1000
    return req


def _rotations_to(D: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotations (n, 3, 3) whose z columns are the directions of the rows of ``D`` (n, 3), and
    the rows' lengths (n,); rows shorter than 1e-12 get the identity (their solid is a sphere)."""
    D = np.asarray(D, dtype=float).reshape(-1, 3)
    length = np.linalg.norm(D, axis=1)
    short = length < 1e-12
    u = np.where(short[:, None], [0.0, 0.0, 1.0], D / np.where(short, 1.0, length)[:, None])
    a = np.where((np.abs(u[:, 0]) < 0.9)[:, None], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    x = a - np.sum(a * u, axis=1)[:, None] * u
    x /= np.linalg.norm(x, axis=1)[:, None]
    y = np.stack([u[:, 1] * x[:, 2] - u[:, 2] * x[:, 1], u[:, 2] * x[:, 0] - u[:, 0] * x[:, 2],
                  u[:, 0] * x[:, 1] - u[:, 1] * x[:, 0]], axis=1)
    return np.stack([x, y, u], axis=2), length


class ExactCavity:
    """The cavity mesh (Center frame) as an FCL BVH, with capsule queries batched over tools.

    Args:
        mesh_Center: the cavity surface in the Center frame (m).
        z_top: cut the mesh at this height (the mouth opening), keeping z <= z_top; None = as
            given.
    """

    def __init__(self, mesh_Center: trimesh.Trimesh, *, z_top: float | None = None):
        mesh = mesh_Center
        if z_top is not None:
            mesh = trimesh.intersections.slice_mesh_plane(
                mesh, plane_normal=[0, 0, -1.0], plane_origin=[0, 0, float(z_top)]
            )
        if len(mesh.faces) == 0:
            raise InputError("mesh", "no triangles left in the cavity below the mouth opening")
        self.mesh = mesh
        self.z_top = z_top
        V = np.ascontiguousarray(mesh.vertices, dtype=float)
        F = np.ascontiguousarray(mesh.faces, dtype=np.int32)
        bvh = coal.BVHModelOBBRSS()
        bvh.beginModel(len(F), len(V))
        bvh.addVertices(V)
        bvh.addTriangles(np.asarray(F, dtype=np.int64))
        bvh.endModel()
        self._mesh_obj = coal.CollisionObject(bvh, coal.Transform3s())
        self._creq = coal.CollisionRequest()
        self._dreq = distance_request()

    @classmethod
    def from_scan(cls, mesh_W: trimesh.Trimesh, fpsm, *, close_open_cuts: bool = True):
        """The reference for an FPSM fitted to ``mesh_W`` (mesh frame): into Center, open cuts
        closed as the fit closes them, cut at the model's top slice."""
        from implantplan.systems.fpsm.oral_mesh import close_open_cuts as _close

        mesh = mesh_W
        if close_open_cuts:
            mesh, _ = _close(mesh)
        mesh = mesh.copy()
        mesh.apply_transform(invert(np.asarray(fpsm.X_WC, dtype=float)))
        return cls(mesh, z_top=fpsm.z_range[1])

    # -- single queries -----------------------------------------------------------------------

    @staticmethod
    def _segment_objects(A: np.ndarray, B: np.ndarray, radius, solid: str = "capsule") -> list:
        """FCL objects of the segments A[k]-B[k] (n, 3): capsules (or solid cylinders) of
        ``radius`` (scalar or (n,)) about them, spheres where a segment has no length. The
        frames are computed for all segments at once (one FCL object each is what is left)."""
        A = np.asarray(A, dtype=float).reshape(-1, 3)
        B = np.asarray(B, dtype=float).reshape(-1, 3)
        r = np.broadcast_to(np.asarray(radius, dtype=float), (len(A),))
        R, length = _rotations_to(B - A)
        centre = 0.5 * (A + B)
        make = coal.Cylinder if solid == "cylinder" else coal.Capsule
        return [
            coal.CollisionObject(coal.Sphere(float(r[k])), coal.Transform3s(np.eye(3), A[k]))
            if length[k] < 1e-12
            else coal.CollisionObject(make(float(r[k]), float(length[k])),
                                      coal.Transform3s(R[k], centre[k]))
            for k in range(len(A))
        ]

    def _collides(self, obj) -> bool:
        return coal.collide(obj, self._mesh_obj, self._creq, coal.CollisionResult()) > 0

    def _distance(self, obj) -> float:
        return float(coal.distance(obj, self._mesh_obj, self._dreq, coal.DistanceResult()))

    # -- batched queries ----------------------------------------------------------------------

    @staticmethod
    def _batch(p0, p1, radius):
        A = np.atleast_2d(np.asarray(p0, dtype=float))
        B = np.atleast_2d(np.asarray(p1, dtype=float))
        A, B = np.broadcast_arrays(A, B)
        if A.shape[-1] != 3 or not (np.all(np.isfinite(A)) and np.all(np.isfinite(B))):
            raise InputError("p0", "expected finite (n, 3) points (m)")
        r = np.broadcast_to(np.asarray(radius, dtype=float), (A.shape[0],))
        if not np.all(np.isfinite(r)) or np.any(r < 0):
            raise InputError("radius", "expected radii >= 0 m")
        return A, B, r

    def capsule_collides(self, p0, p1, radius) -> np.ndarray:
        """(n,) True where the capsule (axis p0-p1, radius) touches the mesh (FCL collide)."""
        A, B, r = self._batch(p0, p1, radius)
        return np.array([self._collides(o) for o in self._segment_objects(A, B, r)], dtype=bool)

    def start_in_tissue(self, p0) -> np.ndarray:
        """(n,) True where p0 is in tissue: the horizontal segment from the Center axis at its
        height to p0 crosses the mesh (module notes; p0 inside the FPSM's slice range)."""
        A = np.atleast_2d(np.asarray(p0, dtype=float))
        out = np.zeros(len(A), dtype=bool)
        off = np.flatnonzero(np.hypot(A[:, 0], A[:, 1]) > 1e-9)
        axis = np.column_stack([np.zeros((len(off), 2)), A[off, 2]])
        out[off] = [self._collides(o) for o in self._segment_objects(axis, A[off], 0.0)]
        return out

    def capsule_clearance(self, p0, p1, radius, *, check_start: bool = True) -> np.ndarray:
        """(n,) exact signed clearance (m) of capsules starting in the cavity (module notes):
        d - r with d the axis's distance to the mesh; -r when the axis touches the mesh or p0
        is in tissue. ``check_start=False`` skips the start's test (a mesh that is not the
        Center-axis star-shaped cavity, e.g. the opened scan of the teleop studies)."""
        A, B, r = self._batch(p0, p1, radius)
        tissue = self.start_in_tissue(A) if check_start else np.zeros(len(A), dtype=bool)
        out = np.empty(len(A))
        for k, axis in enumerate(self._segment_objects(A, B, 0.0)):
            if tissue[k]:
                out[k] = -r[k]
                continue
            if self._collides(axis):
                out[k] = -r[k]
            else:
                out[k] = self._distance(axis) - r[k]
        return out

    def cylinder_clearance(self, p0, p1, radius, *, check_start: bool = True) -> np.ndarray:
        """(n,) exact signed clearance (m) of solid cylinders (axis p0-p1, radius) starting in
        the cavity: FCL's cylinder-to-mesh distance while the cylinder is free; where it
        touches, the value of the capsule about its axis (d - r, or -r where the axis touches or
        p0 is in tissue), negative and at least as deep as the cylinder's contact, since the
        cylinder lies inside that capsule."""
        A, B, r = self._batch(p0, p1, radius)
        tissue = self.start_in_tissue(A) if check_start else np.zeros(len(A), dtype=bool)
        out = np.empty(len(A))
        axes = self._segment_objects(A, B, 0.0)
        solids = self._segment_objects(A, B, r, solid="cylinder")  # frames for all rows at once
        for k, axis in enumerate(axes):
            if tissue[k] or self._collides(axis):
                out[k] = -r[k]
                continue
            obj = solids[k]
            # free: the cylinder's own distance; touching: its axis capsule's (deeper or equal)
            out[k] = self._distance(axis) - r[k] if self._collides(obj) else self._distance(obj)
        return out

    def tool_clearance(self, X_CTool, tool, *, check_start: bool = True) -> np.ndarray:
        """(n,) exact clearance (m) of the whole instrument (every solid of
        :class:`systems.instrument.Instrument`, as it is: capsules and spheres by their axis's
        distance minus the radius, cylinders by :meth:`cylinder_clearance`) at poses (n, 4, 4)
        of T in Center; the smallest over the solids."""
        from implantplan.systems.placement.tool_clearance import rigid_poses

        X = rigid_poses(X_CTool)
        R, p = X[:, :3, :3], X[:, :3, 3]
        out = np.full(X.shape[0], np.inf)
        for s in tool.shapes:
            A = np.einsum("kij,j->ki", R, s.a) + p
            B = np.einsum("kij,j->ki", R, s.b) + p
            if s.kind == "cylinder":
                c = self.cylinder_clearance(A, B, s.radius, check_start=check_start)
            else:
                c = self.capsule_clearance(A, B, s.radius, check_start=check_start)
            out = np.minimum(out, c)
        return out

def registration_errors(safety: SafetySpec, rng: np.random.Generator,
                        samples: int) -> np.ndarray:
    """(samples, 4, 4) E^-1 for ``samples`` draws of the Center frame's registration error E
    (translation ~ N(0, sigma_translation^2) per axis, rotation vector ~ N(0, sigma_rotation^2)
    per axis, about Center's origin; the sigmas are ``safety.registration_sigma_*``): relative
    to the true anatomy a pose X planned in the registered frame is at E^-1 X. The one sampler
    of the registration error (the Monte Carlo below and analyses.studies.accuracy)."""
    t = rng.normal(0.0, safety.registration_sigma_translation, (samples, 3))
    R = rotations(rng.normal(0.0, safety.registration_sigma_rotation, (samples, 3)))
    E_inv = np.zeros((samples, 4, 4))
    E_inv[:, :3, :3] = np.transpose(R, (0, 2, 1))
    E_inv[:, :3, 3] = -np.einsum("nji,nj->ni", R, t)
    E_inv[:, 3, 3] = 1.0
    return E_inv
