"""The Fpsm model: safe distances (Eq. 10-12), line/rod safety (Eq. 13), the mouth-opening rule,
validation and files. Expected values are worked out by hand in the comments."""

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from implantplan.systems.errors import InputError
from implantplan.systems.fpsm.model import Fpsm


@pytest.fixture
def cyl():
    # radius 50 mm, z from 0 to 100 mm, slices every 10 mm
    return Fpsm.cylinder(0.05, 0.0, 0.1, 11)


def test_cylinder_point_safe_distances(cyl):
    pts = np.array(
        [
            [0.0, 0.0, 0.05],  # on the axis: 50 mm to the wall
            [0.03, 0.04, 0.033],  # radius 50 mm: on the wall
            [-0.01, 0.0, 0.1],  # on the top slice: 40 mm
            [0.06, 0.0, 0.02],  # 10 mm outside the wall
            [0.0, 0.0, -0.01],  # 10 mm below the throat end: min(50, -10) mm
            [0.0, 0.0, 0.2],  # above the mouth opening: unconstrained
        ]
    )
    np.testing.assert_allclose(cyl.d_safe(pts), [0.05, 0.0, 0.04, -0.01, -0.01, np.inf], atol=1e-15)


def test_radius_interpolates_linearly_between_slices():
    # Two slices, radii 40 mm at z = 0 and 60 mm at z = 0.1: at z = 25 mm, 40 + 0.25 * 20 = 45.
    f = Fpsm(np.array([0.0, 0.1]), np.array([[0.04] * 6, [0.06] * 6]))
    np.testing.assert_allclose(f.radius_at([0.3, 2.0], 0.025), [0.045, 0.045], atol=1e-15)
    assert np.isnan(f.radius_at(0.0, 0.2))
    # A point 10 mm from the axis at z = 75 mm: rho = 55 mm, d_safe = 45 mm (Eq. 11).
    np.testing.assert_allclose(f.d_safe([0.0, -0.01, 0.075]), 0.045, atol=1e-15)


def test_non_circular_slice_knots_and_shrink():
    rho = np.array([[0.03, 0.04, 0.05, 0.04], [0.03, 0.04, 0.05, 0.04]])
    f = Fpsm(np.array([0.0, 0.01]), rho)
    # Knot k = 2 is at theta = pi: rho = 50 mm there, so the point (-20, 0) mm has 30 mm.
    np.testing.assert_allclose(f.d_safe([-0.02, 0.0, 0.005]), 0.03, atol=1e-15)
    # Knot k = 1 at theta = pi/2: 40 mm, point at 45 mm is 5 mm outside.
    np.testing.assert_allclose(f.d_safe([0.0, 0.045, 0.0]), -0.005, atol=1e-15)
    s = f.shrink(0.035)  # Eq. 12: keeps the 30 mm radii (now -5 mm) rather than failing
    assert s.settings["shrink_m"] == pytest.approx(0.035)
    np.testing.assert_allclose(s.rho, rho - 0.035)
    pts = np.random.default_rng(0).uniform(-0.05, 0.05, (50, 3)) * [1, 1, 0.2] + [0, 0, 0.005]
    np.testing.assert_allclose(s.d_safe(pts), f.d_safe(pts) - 0.035, atol=1e-15)
    np.testing.assert_allclose(f.d_safe(pts, radius=0.035), s.d_safe(pts), atol=1e-15)
    # the shrink is remembered, so the shrunk model survives a round trip
    assert np.all(Fpsm.from_dict(s.to_dict()).rho == s.rho)


def test_vertical_lines_in_cylinder(cyl):
    # Vertical rays at 15.5 mm from the axis, starting at z = 50 mm: every sample has
    # d = 50 - 15.5 = 34.5 mm; crossings at z = 60..100 (5) + T = 6 samples; Eq. 13 with
    # 0.5/0.5 gives 0.5 * 34.5 + 0.5 * 34.5 = 34.5 mm.
    ls = cyl.line_safety([[0, 0.0155, 0.05], [0, -0.0155, 0.05]], [0, 0, 1])
    np.testing.assert_allclose(ls.f_safe, 0.0345, atol=1e-15)
    np.testing.assert_array_equal(ls.samples, [6, 6])
    # A rod of radius 6 mm: against the 44 mm shrunk cylinder, 28.5 mm.
    rod = cyl.line_safety([0, 0.0155, 0.05], [0, 0, 1], radius=0.006)
    np.testing.assert_allclose(rod.f_safe, 0.0285, atol=1e-15)


def test_tilted_line_eq13_by_hand():
    f = Fpsm.cylinder(0.05, 0.0, 0.1, 3)  # slices at 0, 50, 100 mm
    # From the origin along (0.2, 0, 1): T on slice 0 (d = 50 mm, not counted twice), then
    # x = 10 mm at z = 50 (d = 40), x = 20 mm at z = 100 (d = 30): mean 40, min 30.
    ls = f.line_safety([0, 0, 0], [0.2, 0, 1])
    np.testing.assert_allclose(ls.d_safe_mean, 0.04, atol=1e-15)
    np.testing.assert_allclose(ls.d_safe_min, 0.03, atol=1e-15)
    np.testing.assert_allclose(ls.f_safe, 0.035, atol=1e-15)
    assert ls.samples[0] == 3
    ls = f.line_safety([0, 0, 0], [0.2, 0, 1], lambda_avg=0.3, lambda_min=0.7)
    np.testing.assert_allclose(ls.f_safe, 0.3 * 0.04 + 0.7 * 0.03, atol=1e-15)


def test_mouth_opening_rule(cyl):
    start = np.array([0.0, 0.0, 0.05])
    dirs = np.array(
        [
            [0, 0, 1],  # out through the opening: safe
            [1, 0, 0],  # horizontal: leaves through the side
            [0, 0, -1],  # down: leaves through the throat
            [1, 0, 1],  # 45 deg: leaves the side at z = 100 mm exactly (touching: d = 0)
            [2, 0, 1],  # leaves the side at z = 75 mm: crossings above are outside
            [0.1, 0, -1],  # mostly down: throat
        ]
    )
    ls = cyl.line_safety(np.broadcast_to(start, dirs.shape), dirs)
    assert ls.f_safe[0] > 0
    assert np.all(ls.f_safe[1:] <= 0)
    # [2, 0, 1]: the bounding cylinder has radius 1.25 * 50 = 62.5 mm (max_radius); the ray
    # reaches it at x = 62.5 mm, z = 81.25 mm, below the top slice, so it is cut there.
    # Samples: T (50), z = 60 (x = 20: 30), z = 70 (x = 40: 10), z = 80 (x = 60: -10) and the
    # exit point (50 - 62.5 = -12.5 mm); d_min = -12.5 mm and f = 0.5 * d_min.
    np.testing.assert_allclose(ls.d_safe_min[4], -0.0125, atol=1e-15)
    np.testing.assert_allclose(ls.f_safe[4], -0.00625, atol=1e-15)
    assert ls.samples[4] == 5
    # horizontal: T and the exit point at x = 62.5 mm only
    np.testing.assert_allclose(ls.d_safe_min[1], -0.0125, atol=1e-15)
    assert ls.samples[1] == 2


def test_segments_and_lines_above_the_mouth(cyl):
    # A segment that stays inside: T, crossings at 60 and 70 mm, and its end at 75 mm.
    ls = cyl.line_safety([0.01, 0, 0.05], [0, 0, 1], 0.025)
    assert ls.samples[0] == 4 and ls.f_safe[0] == pytest.approx(0.04)
    # A segment sinking below the throat end: its end 10 mm below z_0 is a collision.
    ls = cyl.line_safety([0.0, 0, 0.005], [0, 0, -1], 0.015)
    np.testing.assert_allclose(ls.d_safe_min, -0.01, atol=1e-15)
    # A ray starting above the opening, going out: nothing to check.
    ls = cyl.line_safety([0.0, 0, 0.15], [0, 0, 1])
    assert ls.samples[0] == 0 and ls.f_safe[0] == np.inf
    # ... but one coming back in and ending in the throat is a collision.
    ls = cyl.line_safety([0.0, 0, 0.15], [0, 0, -1])
    assert ls.f_safe[0] < 0


@settings(max_examples=40, deadline=None)
@given(
    starts=arrays(float, (7, 3), elements=st.floats(-0.06, 0.12)),
    dirs=arrays(float, (7, 3), elements=st.floats(-1, 1)),
    radius=st.floats(0.0, 0.01),
)
def test_batched_lines_equal_one_at_a_time(starts, dirs, radius):
    dirs = dirs + np.array([0, 0, 1e-3])  # keep them non-zero
    f = Fpsm(np.array([0.0, 0.03, 0.07, 0.1]), np.random.default_rng(1).uniform(0.03, 0.05, (4, 9)))
    batch = f.line_safety(starts, dirs, radius=radius)
    for k in range(7):
        one = f.line_safety(starts[k], dirs[k], radius=radius)
        np.testing.assert_allclose(one.f_safe[0], batch.f_safe[k], rtol=1e-12, atol=1e-15)
        assert one.samples[0] == batch.samples[k]
    # a safe line has every sample inside: the dense points of the segment to the top are inside
    # up to the sampling between slices, so at least its sampled points must be
    safe = batch.f_safe > 0
    assert np.all(batch.d_safe_min[safe] > 0)


@settings(max_examples=25, deadline=None)
@given(
    rho=arrays(float, (3, 7), elements=st.floats(0.001, 0.08)),
    gaps=arrays(float, (2,), elements=st.floats(1e-4, 0.05)),
    yaw=st.floats(-np.pi, np.pi),
)
def test_save_load_round_trip(tmp_path_factory, rho, gaps, yaw):
    z = np.concatenate([[0.0], np.cumsum(gaps)])
    c, s = np.cos(yaw), np.sin(yaw)
    X = np.array([[c, -s, 0, 0.01], [s, c, 0, -0.02], [0, 0, 1, 0.03], [0, 0, 0, 1.0]])
    f = Fpsm(z, rho, X, {"method": "exact", "N": 7}, {"coverage": [0.9, 0.8, 0.95]})
    path = tmp_path_factory.mktemp("fpsm") / "f.json"
    f.save(path)
    g = Fpsm.load(path)
    np.testing.assert_array_equal(g.rho, f.rho)
    np.testing.assert_array_equal(g.slice_z, f.slice_z)
    np.testing.assert_array_equal(g.X_WC, f.X_WC)
    assert g.settings == f.settings and g.diagnostics == f.diagnostics
    raw = json.loads(path.read_text())
    assert raw["schema_version"] == 1 and raw["kind"] == "fpsm" and raw["units"] == "m"
    assert raw["frame"]["name"] == "Center"


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(slice_z=[0.0, 0.0], rho=np.full((2, 4), 0.01)), "slice_z"),
        (dict(slice_z=[0.0, np.nan], rho=np.full((2, 4), 0.01)), "slice_z"),
        (dict(slice_z=[0.0, 0.1], rho=np.full((3, 4), 0.01)), "rho"),
        (dict(slice_z=[0.0, 0.1], rho=np.full((2, 2), 0.01)), "rho"),
        (dict(slice_z=[0.0, 0.1], rho=[[0.01, np.nan, 0.01], [0.01] * 3]), "rho"),
        (dict(slice_z=[0.0, 0.1], rho=[[0.01, -0.01, 0.01], [0.01] * 3]), "rho"),
        (dict(slice_z=[0.0, 0.1], rho=np.full((2, 3), 0.01), X_WC=np.eye(3)), "X_WC"),
        (dict(slice_z=[0.0, 0.1], rho=np.full((2, 3), 0.01), X_WC=2 * np.eye(4)), "X_WC"),
    ],
)
def test_validation_names_the_field(kwargs, field):
    with pytest.raises(InputError) as err:
        Fpsm(**kwargs)
    assert err.value.field == field


def test_bad_queries_and_files(cyl, tmp_path):
    with pytest.raises(InputError, match="points_Center_m"):
        cyl.d_safe([[np.nan, 0, 0]])
    with pytest.raises(InputError, match="direction"):
        cyl.line_safety([0, 0, 0], [0, 0, 0])
    with pytest.raises(InputError, match="length"):
        cyl.line_safety([0, 0, 0], [0, 0, 1], -1.0)
    with pytest.raises(InputError, match="radius"):
        Fpsm.cylinder(-0.05, 0, 0.1, 3)
    with pytest.raises(InputError, match="fpsm"):
        Fpsm.load(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"schema_version": 1, "kind": "fpsm", "slice_z": [0, 1]}))
    with pytest.raises(InputError, match="rho"):
        Fpsm.load(bad)
    bad.write_text(json.dumps({"schema_version": 1, "kind": "placement"}))
    with pytest.raises(InputError, match="expected 'fpsm'"):
        Fpsm.load(bad)


@settings(max_examples=30, deadline=None)
@given(
    starts=arrays(float, (25, 3), elements=st.floats(-0.08, 0.13)),
    dirs=arrays(float, (25, 3), elements=st.floats(-1, 1)),
    lengths=arrays(float, (25,), elements=st.one_of(st.just(np.inf), st.floats(1e-3, 0.2))),
    radii=arrays(float, (25,), elements=st.floats(0.0, 0.02)),
    shrink=st.floats(0.0, 0.01),
)
def test_compiled_kernel_matches_numpy_reference(starts, dirs, lengths, radii, shrink):
    dirs = dirs + np.array([0, 0, 1e-3])
    u = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    rho = np.random.default_rng(2).uniform(0.03, 0.05, (5, 7))
    f = Fpsm(np.array([0.0, 0.02, 0.05, 0.06, 0.1]), rho).shrink(shrink)
    a = f._line_safety(starts, u, lengths, radii, 0.4, 0.6)
    b = f._line_safety_numpy(starts, u, lengths, radii, 0.4, 0.6)
    np.testing.assert_array_equal(a.samples, b.samples)
    for x, y in (
        (a.f_safe, b.f_safe),
        (a.d_safe_min, b.d_safe_min),
        (a.d_safe_mean, b.d_safe_mean),
    ):
        np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-14)


def test_single_slice_model():
    # One slice of radius 20 mm at z = 10 mm: a point on it 5 mm from the axis has 15 mm;
    # a vertical ray from there crosses nothing above (the slice is the top), so only T counts.
    f = Fpsm(np.array([0.01]), np.full((1, 5), 0.02))
    np.testing.assert_allclose(f.d_safe([[0.005, 0, 0.01], [0, 0, 0.0]]), [0.015, -0.01])
    ls = f.line_safety([0.005, 0, 0.01], [0, 0, 1])
    assert ls.samples[0] == 1 and ls.f_safe[0] == pytest.approx(0.015)
    ref = f._line_safety_numpy(
        np.array([[0.005, 0, 0.01]]), np.array([[0, 0, 1.0]]), np.array([np.inf]), 0.0, 0.5, 0.5
    )
    assert ref.f_safe[0] == pytest.approx(0.015)


def test_kernels_agree_on_the_axis_with_negative_zero():
    """Found by hypothesis: a line starting at (-0, -0, -0) on the axis. atan2(-0, -0) = -pi, so
    without normalizing the sign of zero the two kernels read rho at different angles."""
    rho = np.random.default_rng(2).uniform(0.03, 0.05, (5, 7))
    f = Fpsm(np.array([0.0, 0.02, 0.05, 0.06, 0.1]), rho)
    starts = np.full((2, 3), -0.0)
    u = np.tile([0.0, 0.0, 1.0], (2, 1))
    a = f._line_safety(starts, u, np.full(2, np.inf), np.zeros(2), 0.4, 0.6)
    b = f._line_safety_numpy(starts, u, np.full(2, np.inf), np.zeros(2), 0.4, 0.6)
    np.testing.assert_allclose(a.f_safe, b.f_safe, rtol=1e-12)
    # on the axis every point of a slice is at rho(0) from the wall
    np.testing.assert_allclose(f.d_safe(np.array([[-0.0, -0.0, 0.02]])), rho[1, 0], rtol=1e-12)
