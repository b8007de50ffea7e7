"""The FPSM curve core against the paper's own construction (Eq. 1-6)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from implantplan.systems.fpsm import model as fpsm


def eq3_coefficients(rho: np.ndarray) -> np.ndarray:
    """Solve the paper's linear system M a = b (Eq. 3-5) for the per-segment cubic coefficients
    in absolute theta: rho_i(theta) = a_i + b_i theta + c_i theta^2 + d_i theta^3."""
    n = rho.size
    M = np.zeros((4 * n, 4 * n))
    b = np.zeros(4 * n)
    slope = n * (np.roll(rho, -1) - np.roll(rho, 1)) / (4 * np.pi)  # Eq. 2, at each knot
    for i in range(n):
        t0, t1 = 2 * np.pi * i / n, 2 * np.pi * (i + 1) / n
        c = slice(4 * i, 4 * i + 4)
        M[4 * i + 0, c] = [1, t0, t0**2, t0**3]  # P_i rows (Eq. 4)
        M[4 * i + 1, c] = [1, t1, t1**2, t1**3]
        M[4 * i + 2, c] = [0, 1, 2 * t0, 3 * t0**2]  # Q_i rows
        M[4 * i + 3, c] = [0, 1, 2 * t1, 3 * t1**2]
        b[4 * i : 4 * i + 4] = [rho[i], rho[(i + 1) % n], slope[i], slope[(i + 1) % n]]
    return np.linalg.solve(M, b).reshape(n, 4)


@pytest.mark.parametrize("n", [3, 6, 15, 20])
def test_basis_matches_eq3_solved_directly(n):
    rng = np.random.default_rng(n)
    rho = rng.uniform(0.01, 0.05, n)
    coef = eq3_coefficients(rho)
    theta = rng.uniform(0, 2 * np.pi, 2000)
    seg = np.minimum((theta * n / (2 * np.pi)).astype(int), n - 1)
    expected = np.polynomial.polynomial.polyval(theta, coef[seg].T, tensor=False)
    np.testing.assert_allclose(fpsm.evaluate(rho[None], theta), expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(fpsm.basis_matrix(theta, n) @ rho, expected, rtol=0, atol=1e-12)


def test_curve_interpolates_control_radii_and_is_periodic():
    rho = np.array([1.0, 2.0, 1.5, 3.0, 2.5, 1.2])
    knots = 2 * np.pi * np.arange(6) / 6
    np.testing.assert_allclose(fpsm.evaluate(rho[None], knots), rho, atol=1e-14)
    np.testing.assert_allclose(
        fpsm.evaluate(rho[None], knots + 2 * np.pi), fpsm.evaluate(rho[None], knots), atol=1e-12
    )
    # C1 at every knot: one-sided slopes agree with the central difference of Eq. 2.
    eps = 1e-7
    left = fpsm.derivative(rho[None], knots - eps)
    right = fpsm.derivative(rho[None], knots + eps)
    central = 6 * (np.roll(rho, -1) - np.roll(rho, 1)) / (4 * np.pi)
    np.testing.assert_allclose(left, central, atol=1e-5)
    np.testing.assert_allclose(right, central, atol=1e-5)


def test_circle_area_is_exact():
    for n in (3, 7, 20):
        np.testing.assert_allclose(fpsm.area(np.full(n, 0.05)), np.pi * 0.05**2, rtol=1e-14)


@settings(max_examples=50, deadline=None)
@given(arrays(float, st.integers(3, 24), elements=st.floats(0.001, 0.1)))
def test_area_quadratic_form_matches_quadrature(rho):
    n = rho.size
    # Gauss-Legendre on each segment integrates the degree-6 integrand exactly.
    x, w = np.polynomial.legendre.leggauss(5)
    h = 2 * np.pi / n
    theta = (np.arange(n)[:, None] + (x[None, :] + 1) / 2) * h
    integral = np.sum(fpsm.evaluate(rho[None], theta.ravel()) ** 2 * np.tile(w, n) * h / 2)
    np.testing.assert_allclose(fpsm.area(rho), 0.5 * integral, rtol=1e-12)


def test_area_matrix_is_circulant_and_symmetric():
    Q = fpsm.area_matrix(9)
    np.testing.assert_allclose(Q, Q.T, atol=1e-15)
    for k in range(9):
        np.testing.assert_allclose(np.roll(np.roll(Q, k, 0), k, 1), Q, atol=1e-15)


def test_too_few_control_points_is_an_error():
    with pytest.raises(ValueError, match="control_points"):
        fpsm.basis_weights(0.0, 2)
