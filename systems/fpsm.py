"""Finite-parameter surrogate model (FPSM) of the oral cavity (seed 000, Wang et al. 2023).

The curve of one slice (Eq. 1-5): N control radii rho_1..rho_N at theta_k = 2*pi*k/N
(k = 0..N-1 here, zero-based); on each segment a cubic that takes the control values at its ends
and the central-difference slope v_k = N*(rho_{k+1} - rho_{k-1})/(4*pi) (Eq. 2) at each knot.
That is a periodic cubic Hermite (Catmull-Rom) spline, so rho(theta) is *linear* in the control
radii: rho(theta) = B(theta) . rho, with at most four non-zero weights per angle. We evaluate it
through those weights instead of solving Eq. 3 each time (tests check both give the same curve).

With h = 2*pi/N and t = (theta - theta_k)/h on segment k, the Hermite form gives
    rho = h00 rho_k + h01 rho_{k+1} + h10 (rho_{k+1} - rho_{k-1})/2 + h11 (rho_{k+2} - rho_k)/2,
so the weights on (rho_{k-1}, rho_k, rho_{k+1}, rho_{k+2}) are
    (-h10/2, h00 - h11/2, h01 + h10/2, h11/2).

The area (Eq. 6) S = 1/2 int rho^2 dtheta is then the quadratic form S = 1/2 rho^T Q rho with the
constant circulant Q = int B(theta)^T B(theta) dtheta, computed exactly (:func:`area_matrix`).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

TWO_PI = 2.0 * np.pi

# Catmull-Rom weights on (rho_{k-1}, rho_k, rho_{k+1}, rho_{k+2}) as cubics in t, rows = weight,
# columns = coefficients of (1, t, t^2, t^3). From h00 = 1 - 3t^2 + 2t^3, h10 = t - 2t^2 + t^3,
# h01 = 3t^2 - 2t^3, h11 = -t^2 + t^3.
_W = np.array(
    [
        [0.0, -0.5, 1.0, -0.5],
        [1.0, 0.0, -2.5, 1.5],
        [0.0, 0.5, 2.0, -1.5],
        [0.0, 0.0, -0.5, 0.5],
    ]
)


def _check_n(n: int) -> int:
    n = int(n)
    if n < 3:
        raise ValueError(f"control_points: expected at least 3, got {n}")
    return n


def basis_weights(theta, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Non-zero basis weights of rho(theta) for N = ``n`` control radii.

    Args:
        theta: angles (rad), any shape; wrapped into [0, 2*pi).
        n: number of control radii N (>= 3).

    Returns:
        ``(index, weight)``, both of shape ``theta.shape + (4,)``: rho(theta) =
        sum(weight * rho[..., index]). Indices are in 0..n-1 (periodic).
    """
    n = _check_n(n)
    theta = np.asarray(theta, dtype=float)
    u = np.mod(theta, TWO_PI) * (n / TWO_PI)
    k = np.floor(u).astype(np.int64)
    k = np.minimum(k, n - 1)  # u can round up to exactly n
    t = u - k
    powers = np.stack([np.ones_like(t), t, t * t, t * t * t], axis=-1)
    weight = powers @ _W.T
    index = np.mod(k[..., None] + np.arange(-1, 3), n)
    return index, weight


def basis_matrix(theta, n: int) -> np.ndarray:
    """Dense basis B (len(theta), n) with rho(theta) = B @ rho for 1-D ``theta``."""
    theta = np.atleast_1d(np.asarray(theta, dtype=float))
    index, weight = basis_weights(theta, n)
    B = np.zeros((theta.size, n))
    rows = np.repeat(np.arange(theta.size), 4)
    np.add.at(B, (rows, index.reshape(-1)), weight.reshape(-1))
    return B


def evaluate(rho, theta) -> np.ndarray:
    """rho(theta) for control radii ``rho`` (..., N) at angles ``theta`` broadcastable to (...).

    The leading dimensions of ``rho`` and ``theta`` broadcast: one curve at many angles is
    ``evaluate(rho[None, :], theta)``; many curves each at its own angle is
    ``evaluate(rho_batch, theta_batch)``.
    """
    rho = np.asarray(rho, dtype=float)
    index, weight = basis_weights(theta, rho.shape[-1])
    shape = np.broadcast_shapes(rho.shape[:-1], index.shape[:-1])
    rho_b = np.broadcast_to(rho, shape + rho.shape[-1:])
    index = np.broadcast_to(index, shape + (4,))
    weight = np.broadcast_to(weight, shape + (4,))
    return np.sum(np.take_along_axis(rho_b, index, axis=-1) * weight, axis=-1)


def derivative(rho, theta) -> np.ndarray:
    """d rho / d theta, same broadcasting as :func:`evaluate`."""
    rho = np.asarray(rho, dtype=float)
    n = rho.shape[-1]
    theta = np.asarray(theta, dtype=float)
    u = np.mod(theta, TWO_PI) * (n / TWO_PI)
    k = np.minimum(np.floor(u).astype(np.int64), n - 1)
    t = u - k
    dpowers = np.stack([np.zeros_like(t), np.ones_like(t), 2 * t, 3 * t * t], axis=-1)
    weight = (dpowers @ _W.T) * (n / TWO_PI)
    index = np.mod(k[..., None] + np.arange(-1, 3), n)
    shape = np.broadcast_shapes(rho.shape[:-1], index.shape[:-1])
    rho_b = np.broadcast_to(rho, shape + (n,))
    return np.sum(
        np.take_along_axis(rho_b, np.broadcast_to(index, shape + (4,)), axis=-1)
        * np.broadcast_to(weight, shape + (4,)),
        axis=-1,
    )


@lru_cache(maxsize=64)
def _area_matrix_cached(n: int) -> np.ndarray:
    # Exact Gram matrix of the four local weights over t in [0, 1]:
    # G[a, b] = int_0^1 w_a(t) w_b(t) dt, with w_a(t) = sum_i _W[a, i] t^i.
    moments = 1.0 / (np.add.outer(np.arange(4), np.arange(4)) + 1.0)  # int t^(i+j) dt
    G = _W @ moments @ _W.T
    h = TWO_PI / n
    Q = np.zeros((n, n))
    for k in range(n):
        idx = np.mod(k + np.arange(-1, 3), n)
        np.add.at(Q, (idx[:, None], idx[None, :]), h * G)  # indices repeat when n == 3
    Q.setflags(write=False)
    return Q


def area_matrix(n: int) -> np.ndarray:
    """Constant circulant Q (n, n) with int_0^{2 pi} rho^2 dtheta = rho^T Q rho (exact)."""
    return _area_matrix_cached(_check_n(n))


def area(rho) -> np.ndarray:
    """Area enclosed by the curve (Eq. 6), S = 1/2 rho^T Q rho, batched over leading dims."""
    rho = np.asarray(rho, dtype=float)
    Q = area_matrix(rho.shape[-1])
    return 0.5 * np.einsum("...i,ij,...j->...", rho, Q, rho)
