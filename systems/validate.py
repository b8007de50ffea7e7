"""Validation of user input read from YAML/JSON/CLI: one place for "field: what was expected".

Every check takes the value and the dotted name of the field it came from, and raises
``InputError(field, ...)`` with what was expected; nothing is clamped or guessed.

**Typed schemas.** Every YAML section is a frozen dataclass whose fields are declared with
:func:`spec` (the check, the default, the YAML key and a unit scale); :func:`parse` builds it from
a mapping, rejects unknown keys, names missing required ones and runs each value through its
check with the field's dotted name. Sections nest with :func:`section`, lists of sections with
:func:`sections`, one of several kinds of section with :func:`variant`. Every YAML file the
project reads is read this way: the case (analyses.case), the MOPRP scenario
(systems.robot.scenario), the RASSCMAP inputs (systems.capability.rasscmap_inputs) and the cohort
(analyses.cohort), each after :func:`systems.files.read_yaml` has refused duplicate keys and
aliases.
"""

from __future__ import annotations

import copy
import re
from collections.abc import Callable
from dataclasses import MISSING, field, fields
from functools import partial
from typing import Any

import numpy as np

from implantplan.systems.errors import InputError
from implantplan.systems.jit import numba


def mapping(value: Any, field: str) -> dict:
    """A YAML/JSON mapping (an empty or missing section is an empty dict)."""
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise InputError(field, f"expected a mapping, got {type(value).__name__}")
    return value


def require(d: dict, key: str, where: str = "") -> Any:
    """``d[key]``, or an InputError naming ``where + key`` as missing."""
    if key not in d or d[key] is None:
        raise InputError(f"{where}{key}", "missing (required)")
    return d[key]


def number(
    value: Any,
    field: str,
    *,
    positive: bool = False,
    nonneg: bool = False,
    integer: bool = False,
    low: float | None = None,
    high: float | None = None,
) -> float:
    """A finite number (bools are not), optionally positive/non-negative/whole/within bounds."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise InputError(field, f"expected a number, got {_shown(value)}")
    try:
        v = float(value)
    except OverflowError:  # an integer of hundreds of digits
        v = float("inf")
    shown = _shown(value)
    if not np.isfinite(v):
        raise InputError(field, f"expected a finite number, got {shown}")
    if positive and v <= 0:
        raise InputError(field, f"expected a positive number, got {shown}")
    if nonneg and v < 0:
        raise InputError(field, f"expected a number >= 0, got {shown}")
    if integer and v != int(v):
        raise InputError(field, f"expected a whole number, got {shown}")
    if low is not None and v < low:
        raise InputError(field, f"expected a number >= {low:g}, got {shown}")
    if high is not None and v > high:
        raise InputError(field, f"expected a number <= {high:g} (the documented upper bound), "
                         f"got {shown}")
    return v


def _shown(value: Any, width: int = 40) -> str:
    """``repr(value)`` cut to ``width`` characters (a message stays one short line)."""
    text = repr(value)
    return text if len(text) <= width else f"{text[:width]}... ({len(text)} characters)"


def integer(value: Any, field: str, *, low: int | None = None, high: int | None = None) -> int:
    return int(number(value, field, integer=True, low=low, high=high))


def vector(value: Any, field: str, n: int, *, limit: float | None = None) -> np.ndarray:
    """``n`` finite numbers (with ``limit``: each within [-limit, limit])."""
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError, OverflowError):
        raise InputError(field, f"expected {n} numbers, got {_shown(value)}") from None
    if arr.shape != (n,) or not np.all(np.isfinite(arr)):
        raise InputError(field, f"expected {n} finite numbers, got {_shown(value)}")
    if limit is not None and np.abs(arr).max() > limit:
        raise InputError(field, f"expected {n} numbers within +-{limit:g} (the documented "
                         f"bound), got {_shown(value)}")
    return arr


def interval(value: Any, field: str) -> np.ndarray:
    """``[lower, upper]`` with lower < upper."""
    pair = vector(value, field, 2)
    if not pair[0] < pair[1]:
        raise InputError(field, f"expected [lower, upper] with lower < upper, got {pair.tolist()}")
    return pair


def direction(value: Any, field: str) -> np.ndarray:
    """A non-zero 3-vector, returned normalized."""
    v = vector(value, field, 3)
    norm = float(np.linalg.norm(v))
    if norm < 1e-12:
        raise InputError(field, "expected a non-zero direction")
    return v / norm


ROTATION_TOL = 1e-6  # max |R^T R - I| and |det R - 1| of a pose read from input


def pose(value: Any, field: str, *, batch: bool = False, tol: float = ROTATION_TOL) -> np.ndarray:
    """A rigid transform (4x4), or with ``batch`` poses (..., 4, 4): finite numbers, a proper
    rotation within ``tol`` (orthonormal, det +1) and the last row [0, 0, 0, 1] within ``tol``.
    The one pose validator (kinematics, FPSM, plant, CLI and file inputs)."""
    try:
        X = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise InputError(field, "expected a 4x4 pose matrix of numbers") from None
    if X.shape[-2:] != (4, 4) or X.ndim < 2 or (X.ndim != 2 and not batch):
        what = "poses of shape (..., 4, 4)" if batch else "a 4x4 pose"
        raise InputError(field, f"expected {what}, got shape {X.shape}")
    flat = np.ascontiguousarray(X.reshape(-1, 4, 4))
    err, finite = rotation_error(flat)
    if not finite:
        raise InputError(field, "poses must be finite (found NaN or inf)")
    if err > tol:
        raise InputError(
            field, f"rotation part is not a proper rotation (orthonormality error {err:.1e})"
        )
    if flat.size and np.abs(flat[:, 3] - [0.0, 0.0, 0.0, 1.0]).max() > tol:
        raise InputError(field, "the last row of a pose must be [0, 0, 0, 1]")
    return X


def rotation(value: Any, field: str, *, tol: float = ROTATION_TOL) -> np.ndarray:
    """A 3x3 proper rotation matrix (checked as :func:`pose` checks a pose's rotation part)."""
    try:
        R = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise InputError(field, "expected a 3x3 rotation matrix of numbers") from None
    if R.shape != (3, 3):
        raise InputError(field, f"expected a 3x3 rotation matrix, got shape {R.shape}")
    X = np.eye(4)
    X[:3, :3] = R
    pose(X, field, tol=tol)
    return R


@numba.njit(cache=True)
def rotation_error(X):  # pragma: no cover - compiled
    """max |R^T R - I| and |det R - 1| over a batch of poses (n, 4, 4), and whether all entries
    are finite: :func:`pose`'s test, compiled (the control loops call it from their kernels)."""
    worst = 0.0
    for n in range(X.shape[0]):
        for i in range(4):
            for j in range(4):
                if not np.isfinite(X[n, i, j]):
                    return np.inf, False
        for i in range(3):
            for j in range(i, 3):
                d = X[n, 0, i] * X[n, 0, j] + X[n, 1, i] * X[n, 1, j] + X[n, 2, i] * X[n, 2, j]
                worst = max(worst, abs(d - (1.0 if i == j else 0.0)))
        det = (
            X[n, 0, 0] * (X[n, 1, 1] * X[n, 2, 2] - X[n, 1, 2] * X[n, 2, 1])
            - X[n, 0, 1] * (X[n, 1, 0] * X[n, 2, 2] - X[n, 1, 2] * X[n, 2, 0])
            + X[n, 0, 2] * (X[n, 1, 0] * X[n, 2, 1] - X[n, 1, 1] * X[n, 2, 0])
        )
        worst = max(worst, abs(det - 1.0))
    return worst, True


def choice(value: Any, field: str, options: tuple) -> Any:
    if value not in options:
        raise InputError(field, f"expected one of {', '.join(map(str, options))}, got {value!r}")
    return value


def names(values, field: str, options: tuple) -> tuple:
    """A non-empty sequence of names, each one of ``options`` (a flag's comma-separated list)."""
    if not values:
        raise InputError(field, f"expected names from {', '.join(map(str, options))}")
    for value in values:
        if value not in options:
            raise InputError(field, f"expected names from {', '.join(map(str, options))}, "
                             f"got {value!r}")
    return tuple(values)


def unknown_keys(d: dict, allowed: tuple[str, ...], where: str) -> None:
    """Reject keys that are not known (a typo must not silently fall back to a default)."""
    extra = sorted(set(d) - set(allowed))
    if extra:
        raise InputError(f"{where}{extra[0]}", f"unknown key; expected one of {', '.join(allowed)}")


# -- typed schemas -------------------------------------------------------------------------------

REQUIRED = object()  # spec default: the key must be present (and not null)


def spec(check: Callable[[Any, str], Any], default: Any = REQUIRED, *, key: str | None = None,
         scale: float | None = None, nullable: bool = False):
    """A dataclass field read from YAML by :func:`parse`.

    Args:
        check: ``check(value, field) -> parsed`` (one of this module's checks, or a partial).
        default: the raw value used when the key is missing or null (it goes through ``check``);
            :data:`REQUIRED` makes the key mandatory; None leaves the field None. The same
            default, checked and scaled, is the dataclass field's default, so a section built in
            code (``SafetySpec()``) and one read from an empty mapping are equal.
        key: the YAML key when it differs from the field name (``position_mm`` -> ``position``).
        scale: multiply the checked value (file units -> SI, e.g. 1e-3 for mm).
        nullable: an explicit ``null`` in the file gives None (the setting switched off)
            instead of the default.
    """
    metadata = {"check": check, "default": default, "key": key, "scale": scale,
                "nullable": nullable}
    if default is REQUIRED:
        return field(metadata=metadata)
    value = None if default is None else _scaled(check(default, key or "default"), scale)
    return field(default_factory=partial(copy.deepcopy, value), metadata=metadata)


def _scaled(value: Any, scale: float | None) -> Any:
    return value if scale is None else value * scale


def parse(cls, data: Any, where: str):
    """Build the :func:`spec` dataclass ``cls`` from the mapping ``data`` found at ``where``
    (dotted; "" for the top of a file). An absent section is an empty mapping."""
    prefix = f"{where}." if where else ""
    d = mapping(data, where or "file")
    specs = []
    for f in fields(cls):
        if "check" not in f.metadata:
            if f.default is MISSING and f.default_factory is MISSING:
                raise TypeError(f"{cls.__name__}.{f.name} is neither a spec nor defaulted")
            continue
        specs.append((f.metadata["key"] or f.name, f))
    unknown_keys(d, tuple(k for k, _ in specs), prefix)
    values = {}
    for key, f in specs:
        m = f.metadata
        raw = d.get(key)
        if raw is None and m["nullable"] and key in d:
            values[f.name] = None
            continue
        if raw is None:
            if m["default"] is REQUIRED:
                raise InputError(prefix + key, "missing (required)")
            raw = m["default"]
        if raw is None:
            values[f.name] = None
            continue
        values[f.name] = _scaled(m["check"](raw, prefix + key), m["scale"])
    return cls(**values)


def section(cls) -> Callable[[Any, str], Any]:
    """A check that parses a nested mapping as the schema dataclass ``cls``."""
    return lambda value, where: parse(cls, value, where)


def sections(cls, *, min_items: int = 0) -> Callable[[Any, str], tuple]:
    """A check for a list of mappings, each parsed as ``cls`` (``where[i]`` in errors)."""
    def check(value, where):
        if not isinstance(value, list) or len(value) < min_items:
            raise InputError(where, f"expected a list of at least {min_items} mappings, got "
                             f"{value!r}" if min_items else f"expected a list, got {value!r}")
        return tuple(parse(cls, item, f"{where}[{i}]") for i, item in enumerate(value))
    return check


def variant(tag: str, **classes) -> Callable[[Any, str], Any]:
    """A check for a mapping parsed as one of ``classes``, chosen by the value of its ``tag`` key
    (``type: capsule`` -> ``classes["capsule"]``); each class declares the tag as a field too,
    so the keys of one kind are unknown keys of another."""
    def check(value, where):
        d = mapping(value, where)
        kind = d.get(tag)
        if not isinstance(kind, str) or kind not in classes:
            raise InputError(f"{where}.{tag}", f"expected {' or '.join(classes)}, got {kind!r}")
        return parse(classes[kind], d, where)
    return check


def one_of(*options) -> Callable[[Any, str], Any]:
    """A check: the value is one of ``options``."""
    return lambda value, where: choice(value, where, options)


def boolean(value: Any, field: str) -> bool:
    if not isinstance(value, bool):
        raise InputError(field, f"expected true or false, got {value!r}")
    return value


def text(value: Any, field: str) -> str:
    """A non-empty string."""
    if not isinstance(value, str) or not value:
        raise InputError(field, f"expected a non-empty text, got {value!r}")
    return value


def label(value: Any, field: str) -> str:
    """A name (YAML may read ``36`` as a number: it is taken as the text "36")."""
    if isinstance(value, (dict, list)) or str(value) == "":
        raise InputError(field, f"expected a name, got {value!r}")
    return str(value)


NAME = re.compile(r"[A-Za-z0-9_.-]{1,64}")  # names that become file and folder names


def safe_name(value: Any, field: str) -> str:
    """A :func:`label` that is safe as a file or folder name (sites, cases): 1-64 letters,
    digits, ``-``, ``_`` or ``.``, and not ``.`` or ``..``."""
    name = label(value, field)
    if not NAME.fullmatch(name) or name in (".", ".."):
        shown = name if len(name) <= 40 else f"{name[:40]}... ({len(name)} characters)"
        raise InputError(field, f"expected a name of 1 to 64 letters, digits, '-', '_' or '.' "
                         f"(not '.' or '..'; it becomes a file name), got {shown!r}")
    return name


def version(expected: int) -> Callable[[Any, str], int]:
    """A check: ``schema_version`` equals ``expected``."""
    def check(value, where):
        if value != expected or isinstance(value, bool):
            raise InputError(where, f"expected {expected}, got {value!r}")
        return int(value)
    return check


positive = partial(number, positive=True)
nonneg = partial(number, nonneg=True)
vec3 = partial(vector, n=3)
