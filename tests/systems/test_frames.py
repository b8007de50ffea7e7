"""systems.frames: rigid transforms, elementary rotations, the angle wrap, frames from an axis."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from implantplan.systems.errors import InputError
from implantplan.systems.frames import (
    apply,
    frame_from_z,
    invert,
    rot_x,
    rot_y,
    rot_z,
    rotation_angle,
    rpy_to_rotation,
    transform,
    unit,
    wrap_angle,
)

angles = st.floats(-50.0, 50.0, allow_nan=False)


def test_elementary_rotations_hand_derived():
    # a quarter turn about z takes x to y, about x takes y to z, about y takes z to x
    np.testing.assert_allclose(rot_z(np.pi / 2) @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(rot_x(np.pi / 2) @ [0, 1, 0], [0, 0, 1], atol=1e-15)
    np.testing.assert_allclose(rot_y(np.pi / 2) @ [0, 0, 1], [1, 0, 0], atol=1e-15)
    assert rot_z(np.zeros((4, 2))).shape == (4, 2, 3, 3)


def test_rpy_is_the_urdf_convention():
    r, p, y = 0.3, -0.2, 1.1
    np.testing.assert_allclose(rpy_to_rotation([r, p, y]), rot_z(y) @ rot_y(p) @ rot_x(r))


def test_transform_apply_invert_hand_derived():
    X_AB = transform(rot_z(np.pi / 2), [1.0, 2.0, 3.0])
    # B's x axis is A's y: the point (1, 0, 0) in B is (1, 3, 3) in A
    np.testing.assert_allclose(apply(X_AB, [1.0, 0.0, 0.0]), [1.0, 3.0, 3.0], atol=1e-15)
    np.testing.assert_allclose(invert(X_AB) @ X_AB, np.eye(4), atol=1e-15)
    np.testing.assert_allclose(invert(X_AB)[:3, 3], [-2.0, 1.0, -3.0], atol=1e-15)


@settings(max_examples=100, deadline=None)
@given(angles, angles, angles, st.lists(st.floats(-5, 5), min_size=3, max_size=3))
def test_invert_is_the_inverse(r, p, y, t):
    X = transform(rpy_to_rotation([r, p, y]), t)
    np.testing.assert_allclose(X @ invert(X), np.eye(4), atol=1e-12)
    np.testing.assert_allclose(invert(invert(X)), X, atol=1e-12)


def test_rotation_angle_hand_derived_and_near_pi():
    assert rotation_angle(rot_x(0.7)) == pytest.approx(0.7, abs=1e-15)
    assert rotation_angle(np.eye(3)) == 0.0
    assert rotation_angle(rot_y(np.pi - 1e-9)) == pytest.approx(np.pi - 1e-9, abs=1e-12)
    np.testing.assert_allclose(rotation_angle(rot_z(np.array([0.1, -0.2]))), [0.1, 0.2])


def test_wrap_angle_hand_derived():
    np.testing.assert_array_equal(wrap_angle([0.0, np.pi, -np.pi, 3 * np.pi / 2, -3 * np.pi / 2]),
                                  [0.0, -np.pi, -np.pi, -np.pi / 2, np.pi / 2])
    assert wrap_angle(2 * np.pi + 0.25) == pytest.approx(0.25, abs=1e-15)
    assert wrap_angle(np.zeros((2, 3))).shape == (2, 3)


@settings(max_examples=300, deadline=None)
@given(st.floats(-1e6, 1e6, allow_nan=False))
def test_wrap_angle_range_and_period(a):
    w = float(wrap_angle(a))
    assert -np.pi <= w < np.pi
    # the same direction: cos and sin agree (to the rounding of a large a)
    tol = 1e-9 * max(1.0, abs(a))
    assert abs(np.cos(w) - np.cos(a)) <= tol and abs(np.sin(w) - np.sin(a)) <= tol


@settings(max_examples=300, deadline=None)
@given(st.floats(-np.pi, np.pi, allow_nan=False, exclude_max=True))
def test_wrap_angle_keeps_an_angle_in_range_bit_for_bit(a):
    assert wrap_angle(a) == a


def test_unit_and_its_errors():
    np.testing.assert_allclose(unit([3.0, 0.0, 4.0]), [0.6, 0.0, 0.8])
    with pytest.raises(InputError, match="axis: expected a finite, non-zero"):
        unit([0.0, 0.0, 0.0], field="axis")
    with pytest.raises(InputError, match="axis: expected 3 components"):
        unit([1.0, 0.0], field="axis")


def test_frame_from_z_is_right_handed_with_the_hint():
    X = frame_from_z([1.0, 2.0, 3.0], [0.0, 0.0, 2.0], x_hint=[1.0, 1.0, 0.0])
    R = X[:3, :3]
    np.testing.assert_allclose(R[:, 2], [0, 0, 1])
    np.testing.assert_allclose(R[:, 0], np.array([1.0, 1.0, 0.0]) / np.sqrt(2))
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-15)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(X[:3, 3], [1.0, 2.0, 3.0])
    # z along world x: the default hint (world x) is swapped for world y
    np.testing.assert_allclose(frame_from_z(np.zeros(3), [1.0, 0.0, 0.0])[:3, 0], [0, 1, 0])
    with pytest.raises(InputError, match="x_hint"):
        frame_from_z(np.zeros(3), [0, 0, 1], x_hint=[0, 0, -3])


def test_rotation_vector_inverts_rotations():
    """rotation_vector(rotations(w)) = w for angles up to pi - 1e-3 and down to 1e-9."""
    from implantplan.systems.frames import rotation_vector, rotations

    rng = np.random.default_rng(3)
    axes = rng.normal(size=(200, 3))
    axes /= np.linalg.norm(axes, axis=1)[:, None]
    angles = np.concatenate([np.geomspace(1e-9, 1e-2, 50), rng.uniform(0.0, np.pi - 1e-3, 150)])
    w = axes * angles[:, None]
    got = np.array([rotation_vector(R) for R in rotations(w)])
    np.testing.assert_allclose(got, w, atol=1e-9)
    assert np.all(rotation_vector(np.eye(3)) == 0.0)


def test_one_rotation_vector_is_the_batched_formula():
    """rotations of one vector (scalar path) equals the batched Rodrigues to rounding, and is a
    rotation; the zero vector gives the identity exactly."""
    from implantplan.systems.frames import rotations

    rng = np.random.default_rng(11)
    w = rng.normal(size=(300, 3)) * rng.uniform(0.0, 3.1, (300, 1))
    w[:20] *= 1e-9
    batched = rotations(w)
    one = np.array([rotations(v[None])[0] for v in w])
    np.testing.assert_allclose(one, batched, atol=4e-16)
    np.testing.assert_allclose(one @ np.swapaxes(one, 1, 2), np.broadcast_to(np.eye(3), one.shape),
                               atol=1e-15)
    assert np.array_equal(rotations(np.zeros((1, 3))), np.eye(3)[None])
