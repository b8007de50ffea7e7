"""Validation of user input read from YAML/JSON/CLI: one place for "field: what was expected".

Every function takes the value and the dotted name of the field it came from, and raises
``InputError(field, ...)`` with what was expected; nothing is clamped or guessed.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from implantplan.systems.errors import InputError


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
        raise InputError(field, f"expected a number, got {value!r}")
    v = float(value)
    if not np.isfinite(v):
        raise InputError(field, f"expected a finite number, got {value!r}")
    if positive and v <= 0:
        raise InputError(field, f"expected a positive number, got {value!r}")
    if nonneg and v < 0:
        raise InputError(field, f"expected a number >= 0, got {value!r}")
    if integer and v != int(v):
        raise InputError(field, f"expected a whole number, got {value!r}")
    if low is not None and v < low:
        raise InputError(field, f"expected a number >= {low}, got {value!r}")
    if high is not None and v > high:
        raise InputError(field, f"expected a number <= {high}, got {value!r}")
    return v


def integer(value: Any, field: str, *, low: int | None = None) -> int:
    return int(number(value, field, integer=True, low=low))


def vector(value: Any, field: str, n: int) -> np.ndarray:
    """``n`` finite numbers."""
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise InputError(field, f"expected {n} numbers, got {value!r}") from None
    if arr.shape != (n,) or not np.all(np.isfinite(arr)):
        raise InputError(field, f"expected {n} finite numbers, got {value!r}")
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


def choice(value: Any, field: str, options: tuple) -> Any:
    if value not in options:
        raise InputError(field, f"expected one of {', '.join(map(str, options))}, got {value!r}")
    return value


def unknown_keys(d: dict, allowed: tuple[str, ...], where: str) -> None:
    """Reject keys that are not known (a typo must not silently fall back to a default)."""
    extra = sorted(set(d) - set(allowed))
    if extra:
        raise InputError(f"{where}{extra[0]}", f"unknown key; expected one of {', '.join(allowed)}")
