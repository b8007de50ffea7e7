"""The exact reference (ExactCavity, Coal) against an independent one: libigl's exact
point-to-mesh distance at dense samples of each solid's surface, on the bundled scan.

For a solid that does not touch the mesh, its distance to the mesh is the smallest distance of a
point of its surface. Samples of the surface spaced so that every surface point lies within
``delta`` of one give, by the 1-Lipschitz distance function, min over samples - delta <= true
distance <= min over samples. The reference must lie in that interval (up to its GJK gap): never
above the samples (an overestimate is on the unsafe side of every margin), never more than
``delta`` below them (tight)."""

from pathlib import Path

import igl
import numpy as np
import pytest
import trimesh

from implantplan.systems.placement.exact_clearance import REFERENCE_ERROR, ExactCavity

SCAN = Path(__file__).resolve().parents[3] / "models" / "oral" / "oralCavityMesh.obj"


@pytest.fixture(scope="module")
def scan():
    mesh = trimesh.load(SCAN, process=False)
    mesh.apply_scale(1e-3)  # the scan is in mm
    return ExactCavity(mesh)


def _frame(u):
    e1 = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(u, e1)


def cylinder_surface(a, b, r, step):
    """Points of the surface of the solid cylinder (axis a-b, radius r) with every surface point
    within ``step`` of one; and that distance bound."""
    L = np.linalg.norm(b - a)
    u = (b - a) / L
    e1, e2 = _frame(u)
    n_phi = max(8, int(np.ceil(2 * np.pi * r / step)))
    n_t = max(2, int(np.ceil(L / step)) + 1)
    phi = np.arange(n_phi) * 2 * np.pi / n_phi
    ring = np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2
    t = np.linspace(0.0, 1.0, n_t)
    side = (a + t[:, None, None] * (b - a) + r * ring[None]).reshape(-1, 3)
    n_rho = max(2, int(np.ceil(r / step)) + 1)
    rho = np.linspace(0.0, r, n_rho)
    caps = np.vstack([(c + rho[:, None, None] * ring[None]).reshape(-1, 3) for c in (a, b)])
    # a point of the side is within half a chord and half a step of the nearest sample; a cap
    # point within half a ring step and half an arc at radius r
    half_arc = np.pi * r / n_phi
    delta = np.hypot(half_arc, 0.5 * L / (n_t - 1))
    delta = max(delta, np.hypot(half_arc, 0.5 * r / (n_rho - 1)))
    return np.vstack([side, caps]), delta


def point_distance(cav, P):
    return np.sqrt(igl.point_mesh_squared_distance(
        np.ascontiguousarray(P), np.ascontiguousarray(cav.mesh.vertices),
        np.ascontiguousarray(cav.mesh.faces, dtype=np.int64))[0])


def _near_wall_solids(cav, rng, n, radius, length):
    """(a, b) of ``n`` solids with a random axis direction, their centre 0.2-3 mm plus their
    bounding radius inside the wall from a random surface point (most are free)."""
    pts, fi = trimesh.sample.sample_surface(cav.mesh, 4 * n, seed=int(rng.integers(1 << 31)))
    normals = cav.mesh.face_normals[fi]
    out = []
    for p, nrm in zip(pts, normals, strict=True):
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        # the cavity lies on either side of a face; try both and keep the free one
        gap = rng.uniform(0.2e-3, 3e-3) + np.hypot(radius, 0.5 * length)
        for sgn in (1.0, -1.0):
            c = p + sgn * gap * nrm
            a, b = c - 0.5 * length * u, c + 0.5 * length * u
            if not cav.capsule_collides(a, b, radius)[0]:
                out.append((a, b))
                break
        if len(out) == n:
            break
    return out


SHAPES = [(8e-3, 14e-3), (2e-3, 24e-3), (6e-3, 40e-3)]  # the actuator's head, implant, rod


def _check_cylinders(scan, radius, length, n, step, seed):
    rng = np.random.default_rng(seed)
    solids = _near_wall_solids(scan, rng, n, radius, length)
    assert len(solids) >= 0.8 * n
    gaps = []
    for a, b in solids:
        ref = scan.cylinder_clearance(a, b, radius, check_start=False)[0]
        P, delta = cylinder_surface(a, b, radius, step)
        d = point_distance(scan, P).min()
        assert ref <= d + REFERENCE_ERROR, (ref, d)  # never above a point of the solid
        assert ref >= d - delta - REFERENCE_ERROR, (ref, d, delta)  # and tight
        gaps.append(d - ref)
    assert max(gaps) <= 0.03e-3


@pytest.mark.parametrize("radius,length", SHAPES, ids=["head", "implant", "rod"])
def test_cylinder_distance_lies_between_the_surface_samples_and_their_spacing(scan, radius,
                                                                               length):
    _check_cylinders(scan, radius, length, 5, 0.15e-3, seed=int(radius * 1e6) + 7)


@pytest.mark.sweep
@pytest.mark.parametrize("radius,length", SHAPES, ids=["head", "implant", "rod"])
def test_cylinder_distance_on_many_solids_with_fine_samples(scan, radius, length):
    _check_cylinders(scan, radius, length, 20, 0.08e-3, seed=int(radius * 1e6) + 8)


def test_the_head_near_the_margin_where_python_fcl_was_high(scan):
    """The actuator's head (r 8 mm x 14 mm) with its side 0.95 mm over a point of the scan
    (python-fcl's GJK answered about 5 % high at such poses): the reference agrees with the
    samples to their spacing."""
    rng = np.random.default_rng(3)
    p, fi = trimesh.sample.sample_surface(scan.mesh, 1, seed=11)
    nrm = scan.mesh.face_normals[fi[0]]
    u = np.cross(nrm, rng.normal(size=3))
    u /= np.linalg.norm(u)
    for sgn in (1.0, -1.0):
        c = p[0] + sgn * (8e-3 + 0.95e-3) * nrm  # the side wall's rim over the face
        a, b = c - 7e-3 * u, c + 7e-3 * u
        if not scan.capsule_collides(a, b, 8e-3)[0]:
            break
    ref = scan.cylinder_clearance(a, b, 8e-3, check_start=False)[0]
    P, delta = cylinder_surface(a, b, 8e-3, 0.05e-3)
    d = point_distance(scan, P).min()
    assert d - delta - REFERENCE_ERROR <= ref <= d + REFERENCE_ERROR


def test_capsule_distance_is_the_axis_distance_less_the_radius(scan):
    rng = np.random.default_rng(5)
    for a, b in _near_wall_solids(scan, rng, 20, 3e-3, 20e-3):
        ref = scan.capsule_clearance(a, b, 3e-3, check_start=False)[0]
        t = np.linspace(0.0, 1.0, 2001)
        axis = a + t[:, None] * (b - a)
        d = point_distance(scan, axis).min()
        delta = 0.5 * np.linalg.norm(b - a) / 2000
        assert d - delta - REFERENCE_ERROR <= ref + 3e-3 <= d + REFERENCE_ERROR
