"""Validation of user input read from YAML/JSON/CLI: one place for "field: what was expected".

Every function takes the value and the dotted name of the field it came from, and raises
``InputError(field, ...)`` with what was expected; nothing is clamped or guessed.
"""

from __future__ import annotations

from typing import Any

import numba
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
    err, finite = _rotation_error(flat)
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
def _rotation_error(X):  # pragma: no cover - compiled
    """max |R^T R - I| and |det R - 1| over a batch of poses, and whether all entries are finite."""
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


def unknown_keys(d: dict, allowed: tuple[str, ...], where: str) -> None:
    """Reject keys that are not known (a typo must not silently fall back to a default)."""
    extra = sorted(set(d) - set(allowed))
    if extra:
        raise InputError(f"{where}{extra[0]}", f"unknown key; expected one of {', '.join(allowed)}")
