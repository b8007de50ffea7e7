"""The one instrument: the shipped URDF's solids in the Tool frame (by hand), the paper's thin
tool, the capsule cover (contains every solid: exact point tests), and the exact FCL clearance of
cylinders against a mesh (against a brute-force distance)."""

import numpy as np
import pytest
import trimesh

from implantplan.systems.errors import InputError
from implantplan.systems.instrument import Instrument, Shape
from implantplan.systems.placement.exact_clearance import ExactCavity

MM = 1e-3


def test_the_shipped_actuator_by_hand():
    inst = Instrument.actuator()
    shapes = {s.name: s for s in inst.shapes}
    assert set(shapes) == {"rod", "head", "implant"}
    rod, head, implant = shapes["rod"], shapes["head"], shapes["implant"]
    # rod: flange face (x = 160 mm) to 4 mm short of the TCP, along Tool x, r 6 mm
    assert rod.kind == "cylinder" and rod.radius == pytest.approx(6 * MM)
    assert sorted([rod.a[0], rod.b[0]]) == pytest.approx([4 * MM, 160 * MM])
    assert np.allclose(rod.a[1:], 0) and np.allclose(rod.b[1:], 0)
    # head: r 8 mm x 14 mm, coaxial with the implant (Tool z), centred on the TCP
    assert head.kind == "cylinder" and head.radius == pytest.approx(8 * MM)
    assert sorted([head.a[2], head.b[2]]) == pytest.approx([-7 * MM, 7 * MM])
    assert np.allclose(head.a[:2], 0, atol=1e-15)
    # implant: r 2 mm from the head's bottom to the tip 31 mm (d12) below the TCP
    assert sorted([implant.a[2], implant.b[2]]) == pytest.approx([-31 * MM, -7 * MM])
    assert inst.implant_length == pytest.approx(31 * MM) and inst.rod_radius == 6 * MM
    assert inst.head == pytest.approx(8 * MM) and inst.line_offset == 0.0


def test_the_paper_tool_is_seed_000s_lines():
    p = Instrument.paper(rod_radius=5 * MM, implant_length=30 * MM, rod_length=0.2)
    a, b, r = p.capsules_T()
    np.testing.assert_allclose(a, [[5 * MM, 0, 0], [0, 0, 0], [5 * MM, 0, 0]])
    np.testing.assert_allclose(b, [[0.205, 0, 0], [0, 0, 0], [5 * MM, 0, -30 * MM]])
    np.testing.assert_allclose(r, [5 * MM, 5 * MM, 0.0])
    starts, u = p.lines_T()
    np.testing.assert_allclose(starts, [[5 * MM, 0, 0], [5 * MM, 0, -30 * MM]])
    np.testing.assert_allclose(u, [1, 0, 0])
    with pytest.raises(InputError, match="instrument.rod_radius"):
        Instrument.paper(rod_radius=-1)


def _inside_cylinder(shape, P):
    u = (shape.b - shape.a) / shape.length
    t = (P - shape.a) @ u
    radial = np.linalg.norm(P - shape.a - t[:, None] * u, axis=1)
    return (t >= 0) & (t <= shape.length) & (radial <= shape.radius)


def _in_capsules(A, B, r, P):
    d = B - A
    t = np.clip(np.einsum("ncj,cj->nc", P[:, None] - A, d) / np.einsum("cj,cj->c", d, d), 0, 1)
    closest = A + t[..., None] * d
    return (np.linalg.norm(P[:, None] - closest, axis=2) <= r + 1e-12).any(axis=1)


@pytest.mark.parametrize("radius", [3 * MM, 8 * MM, 12 * MM])
def test_the_cover_contains_the_cylinder(radius):
    rng = np.random.default_rng(1)
    axis = rng.normal(size=3)
    shape = Shape("c", "cylinder", [0.01, -0.02, 0.0], 0.014 * axis / np.linalg.norm(axis),
                  radius)
    A, B, r = shape.cover()
    assert len(r) == (1 if radius <= 7 * MM else 7)
    # the worst points: the rim circles and dense samples of the solid
    P = rng.uniform(-1, 1, (200_000, 3)) * 0.03
    P = P[_inside_cylinder(shape, P)]
    u = (shape.b - shape.a) / shape.length
    e1 = np.cross(u, [1, 0, 0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(u, e1)
    ang = np.linspace(0, 2 * np.pi, 3600)
    rim = radius * (np.cos(ang)[:, None] * e1 + np.sin(ang)[:, None] * e2)
    P = np.vstack([P, shape.a + rim, shape.b + rim])
    assert len(P) > 1000 and _in_capsules(A, B, r, P).all()
    # the overshoot beyond a flat end is the cover's radius (R, or R/2 for a wide cylinder)
    assert r.max() == pytest.approx(radius if radius <= 7 * MM else radius / 2)
    assert not _in_capsules(A, B, r, (shape.b + 1.01 * r.max() * u)[None]).any()


def test_cylinder_clearance_is_exact_against_a_plane():
    # a floor (two big triangles at z = 0) and a cylinder r 8 mm x 14 mm tilted by 30 deg: the
    # lowest point of a tilted cylinder is on its bottom rim, z_c - (h/2) cos(t) - r sin(t)
    floor = trimesh.Trimesh([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]],
                            [[0, 1, 2], [0, 2, 3]])
    cavity = ExactCavity(floor)
    t, zc, r, h = np.radians(30), 0.03, 8 * MM, 14 * MM
    u = np.array([np.sin(t), 0, np.cos(t)])
    c = np.array([0.0, 0.0, zc])
    d = cavity.cylinder_clearance(c - 0.5 * h * u, c + 0.5 * h * u, r, check_start=False)
    expected = zc - 0.5 * h * np.cos(t) - r * np.sin(t)
    assert d[0] == pytest.approx(expected, abs=1e-6)
    # the capsule about the same axis says less (its cap reaches lower): the cylinder is tighter
    cap = cavity.capsule_clearance(c - 0.5 * h * u, c + 0.5 * h * u, r, check_start=False)
    assert cap[0] < d[0] - 1e-3
    # touching: negative
    low = c - [0, 0, 0.026]
    assert cavity.cylinder_clearance(low - 0.5 * h * u, low + 0.5 * h * u, r,
                                     check_start=False)[0] < 0


def test_the_fast_bound_of_the_actuator_is_sound_against_fcl_on_the_fpsm_boundary():
    # The FPSM bound of the real instrument (its capsule cover) never exceeds the exact
    # clearance of its solids (FCL) to the FPSM's own boundary: random poses in a cylinder FPSM
    # of radius 50 mm, tilted and placed so most are near a wall.
    from implantplan.systems.fpsm.model import Fpsm
    from implantplan.systems.frames import rotations
    from implantplan.systems.placement.tool_clearance import ToolClearance, boundary_mesh

    fpsm = Fpsm.cylinder(0.05, 0.0, 0.1, 11)
    exact = ExactCavity(boundary_mesh(fpsm, angles=512))  # chord sag 0.94 um
    inst = Instrument.actuator()
    rng = np.random.default_rng(7)
    n = 160
    X = np.repeat(np.eye(4)[None], n, axis=0)
    # the rod pointing out of the mouth (+z) tilted by up to 60 deg, the head 10..40 mm from
    # the axis, 35..80 mm high
    base = np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])  # Tool x = Center z
    X[:, :3, :3] = rotations(rng.normal(size=(n, 3)) * 0.6) @ base
    ang = rng.uniform(0, 2 * np.pi, n)
    rad = rng.uniform(0.0, 0.04, n)
    X[:, :3, 3] = np.c_[rad * np.cos(ang), rad * np.sin(ang), rng.uniform(0.035, 0.08, n)]
    bound = ToolClearance(fpsm, inst)(X)
    truth = exact.tool_clearance(X, inst, check_start=False)
    free = truth > 0
    assert free.sum() > 30 and (~free).sum() > 30  # both kinds are sampled
    assert np.all(bound[free] <= truth[free] + 2e-6)  # never above exact (+ chord sag)
    assert not np.any((bound > 0) & ~free)  # never "free" where a solid touches
    assert np.any(bound[free] > 0)  # and not vacuous: it certifies free poses


@pytest.mark.parametrize("seed", range(4))
def test_the_reach_from_the_rod_axis_bounds_every_point_of_each_solid_tightly(seed):
    """shape_reach_T (the region's rotation loss per solid) is at least the distance of every
    point of the solid from Tool x and within 0.02 mm of the farthest one: random cylinders
    and capsules, dense interior samples and the rims (a rim point is where a cylinder's
    maximum sits)."""
    rng = np.random.default_rng(seed)
    shapes = []
    for kind in ("cylinder", "capsule", "cylinder"):
        a = rng.uniform(-0.02, 0.02, 3)
        b = a + rng.normal(size=3) * 0.01
        shapes.append(Shape(kind, kind, a, b, float(rng.uniform(1, 9)) * MM))
    tool = Instrument("random", tuple(shapes), rod_radius=0.003, implant_length=0.02,
                      rod_length=0.1)
    reach = tool.shape_reach_T()
    for s, r in zip(shapes, reach, strict=True):
        u = (s.b - s.a) / s.length
        e1 = np.cross(u, [1, 0, 0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(u, e1)
        ang = rng.uniform(0, 2 * np.pi, 20_000)
        rim = s.radius * (np.cos(ang)[:, None] * e1 + np.sin(ang)[:, None] * e2)
        if s.kind == "cylinder":
            P = np.vstack([s.a + rim, s.b + rim])
        else:  # the end spheres
            d = rng.normal(size=(40_000, 3))
            d /= np.linalg.norm(d, axis=1)[:, None]
            P = np.vstack([s.a + s.radius * d[:20_000], s.b + s.radius * d[20_000:]])
        far = np.hypot(P[:, 1], P[:, 2]).max()
        assert far <= r + 1e-12
        assert r - far < 0.02 * MM
