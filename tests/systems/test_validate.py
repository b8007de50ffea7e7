"""systems.validate: the field-named checks, the one pose validator and the typed schemas."""

from dataclasses import dataclass

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from implantplan.systems import validate as v
from implantplan.systems.errors import InputError
from implantplan.systems.frames import rot_x, rpy_to_rotation, transform


def test_number_checks_name_the_field():
    assert v.number(2, "a.b") == 2.0
    for bad, kwargs, what in [(True, {}, "expected a number"), ("1", {}, "expected a number"),
                              (float("nan"), {}, "finite"), (0, {"positive": True}, "positive"),
                              (-1, {"nonneg": True}, ">= 0"), (1.5, {"integer": True}, "whole"),
                              (3, {"high": 2}, "<= 2")]:
        with pytest.raises(InputError, match=f"a.b: .*{what}"):
            v.number(bad, "a.b", **kwargs)


def test_vector_interval_direction_choice_unknown_keys():
    np.testing.assert_array_equal(v.vector([1, 2, 3], "p", 3), [1.0, 2.0, 3.0])
    with pytest.raises(InputError, match="p: expected 3 finite numbers"):
        v.vector([1, 2], "p", 3)
    with pytest.raises(InputError, match="lower < upper"):
        v.interval([2, 1], "r")
    np.testing.assert_allclose(v.direction([0, 0, 5], "d"), [0, 0, 1])
    with pytest.raises(InputError, match="non-zero"):
        v.direction([0, 0, 0], "d")
    with pytest.raises(InputError, match="m: expected one of a, b"):
        v.choice("c", "m", ("a", "b"))
    with pytest.raises(InputError, match="s.typo: unknown key"):
        v.unknown_keys({"typo": 1, "ok": 2}, ("ok",), "s.")


def test_pose_accepts_rigid_transforms_and_names_what_is_wrong():
    X = transform(rot_x(0.3), [1.0, 2.0, 3.0])
    assert v.pose(X, "X") is not None
    assert v.pose(np.stack([X, X]), "X", batch=True).shape == (2, 4, 4)
    cases = [
        (np.diag([1.0, 1.0, -1.0, 1.0]), "proper rotation"),  # a reflection, det -1
        (np.diag([2.0, 1.0, 1.0, 1.0]), "proper rotation"),  # a scale
        (np.where(np.eye(4) > 0, np.nan, 0.0), "finite"),
        (np.vstack([X[:3], [0.0, 0.0, 1.0, 1.0]]), "last row"),
        (np.eye(3), "a 4x4 pose"),
        ("not a matrix", "numbers"),
    ]
    for bad, what in cases:
        with pytest.raises(InputError, match=f"X_WC: .*{what}"):
            v.pose(bad, "X_WC")
    with pytest.raises(InputError, match=r"poses of shape \(\.\.\., 4, 4\)"):
        v.pose(np.zeros((2, 3, 3)), "X", batch=True)
    with pytest.raises(InputError, match="a 4x4 pose"):
        v.pose(np.stack([X, X]), "X")  # a batch where one pose is expected


@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(-10, 10), min_size=3, max_size=3),
       st.floats(1e-5, 1e-2))
def test_pose_tolerance_is_the_orthonormality_error(rpy, eps):
    """A rotation scaled by (1 + eps) has |R^T R - I| ~ 2 eps: rejected at the default 1e-6."""
    R = rpy_to_rotation(rpy)
    v.pose(transform(R, np.zeros(3)), "X")
    with pytest.raises(InputError, match="orthonormality error"):
        v.pose(transform(R * (1 + eps), np.zeros(3)), "X")


def test_rotation():
    np.testing.assert_array_equal(v.rotation(np.eye(3), "R_WM"), np.eye(3))
    with pytest.raises(InputError, match="R_WM: expected a 3x3"):
        v.rotation(np.eye(4), "R_WM")
    with pytest.raises(InputError, match="R_WM: rotation part"):
        v.rotation(-np.eye(3), "R_WM")


@dataclass(frozen=True)
class Inner:
    length: float = v.spec(v.positive, 12.0, key="length_mm", scale=1e-3)
    axis: np.ndarray | None = v.spec(v.direction, None)


@dataclass(frozen=True)
class Outer:
    schema_version: int = v.spec(v.version(1))
    name: str = v.spec(v.label)
    mode: str = v.spec(v.one_of("fast", "exact"), "exact")
    flag: bool = v.spec(v.boolean, False)
    inner: Inner = v.spec(v.section(Inner), {})
    items: tuple = v.spec(v.sections(Inner, min_items=1), [{"length_mm": 1}])


def test_parse_reads_defaults_keys_and_scales():
    o = v.parse(Outer, {"schema_version": 1, "name": 36, "inner": {"length_mm": 20},
                        "items": [{}, {"axis": [0, 0, 2]}]}, "")
    assert o.name == "36" and o.mode == "exact" and o.flag is False
    assert o.inner.length == pytest.approx(0.020) and o.inner.axis is None
    assert len(o.items) == 2 and o.items[0].length == pytest.approx(0.012)
    np.testing.assert_allclose(o.items[1].axis, [0, 0, 1])
    d = v.parse(Outer, {"schema_version": 1, "name": "x"}, "")
    assert d.inner == Inner(length=pytest.approx(0.012), axis=None)
    assert d.items[0].length == pytest.approx(0.001)


@pytest.mark.parametrize("data, message", [
    ({"name": "x"}, r"schema_version: missing \(required\)"),
    ({"schema_version": 2, "name": "x"}, "schema_version: expected 1, got 2"),
    ({"schema_version": 1}, r"name: missing \(required\)"),
    ({"schema_version": 1, "name": "x", "mdoe": "fast"}, "mdoe: unknown key"),
    ({"schema_version": 1, "name": "x", "mode": "slow"}, "mode: expected one of fast, exact"),
    ({"schema_version": 1, "name": "x", "flag": "yes"}, "flag: expected true or false"),
    ({"schema_version": 1, "name": "x", "inner": {"length_mm": -1}},
     "inner.length_mm: expected a positive number"),
    ({"schema_version": 1, "name": "x", "inner": {"lenght_mm": 1}}, "inner.lenght_mm: unknown"),
    ({"schema_version": 1, "name": "x", "inner": [1]}, "inner: expected a mapping"),
    ({"schema_version": 1, "name": "x", "items": []}, "items: expected a list of at least 1"),
    ({"schema_version": 1, "name": "x", "items": [{}, {"axis": [0, 0, 0]}]},
     r"items\[1\].axis: expected a non-zero direction"),
])
def test_parse_errors_name_the_field(data, message):
    with pytest.raises(InputError, match=message):
        v.parse(Outer, data, "")


def test_parse_prefixes_nested_fields_with_where():
    with pytest.raises(InputError, match=r"case\.inner\.length_mm"):
        v.parse(Outer, {"schema_version": 1, "name": "x", "inner": {"length_mm": 0}}, "case")


def test_a_section_built_in_code_has_the_files_defaults():
    # the spec's default is the field's default, checked and scaled once
    assert Inner() == v.parse(Inner, {}, "inner")
    assert Inner().length == pytest.approx(0.012) and Inner().axis is None
    assert Outer(schema_version=1, name="x").items[0].length == pytest.approx(0.001)
    with pytest.raises(TypeError):
        Outer(name="x")  # a required key has no default


@dataclass(frozen=True)
class Stop:
    patience: int | None = v.spec(v.integer, 20, nullable=True)
    rate: float = v.spec(v.positive, 2.0)


def test_nullable_takes_an_explicit_null_as_off():
    assert v.parse(Stop, {}, "ga").patience == 20
    assert v.parse(Stop, {"patience": None}, "ga").patience is None
    assert v.parse(Stop, {"rate": None}, "ga").rate == 2.0  # not nullable: null is the default


@dataclass(frozen=True, kw_only=True)
class Ball:
    type: str = v.spec(v.one_of("ball"))
    radius: float = v.spec(v.positive, key="radius_m")


@dataclass(frozen=True, kw_only=True)
class Block:
    type: str = v.spec(v.one_of("block"))
    size: np.ndarray = v.spec(v.vec3, key="size_m")


def test_variant_picks_the_section_by_its_tag_and_names_the_field():
    shape = v.variant("type", ball=Ball, block=Block)
    assert shape({"type": "ball", "radius_m": 1}, "shapes[0]") == Ball(type="ball", radius=1.0)
    assert isinstance(shape({"type": "block", "size_m": [1, 2, 3]}, "s"), Block)
    with pytest.raises(InputError, match=r"shapes\[1\]\.type: expected ball or block, got 'cone'"):
        shape({"type": "cone"}, "shapes[1]")
    with pytest.raises(InputError, match=r"shapes\[1\]\.size_m: unknown key"):
        shape({"type": "ball", "radius_m": 1, "size_m": [1, 2, 3]}, "shapes[1]")
    with pytest.raises(InputError, match=r"s\.radius_m: missing"):
        shape({"type": "ball"}, "s")
