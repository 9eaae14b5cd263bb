"""The second-order balance model (AIAA R-091 spirit): fit, refusal, application, in the core."""

from __future__ import annotations

import numpy as np
import pytest

from cdpr.analysis.balance_model import (
    apply_balance_model,
    fit_second_order,
    quadratic_terms,
)


def _pair(i: int, j: int) -> int:
    """Index of W_i W_j (i <= j) in the row-major upper triangle, counted by hand."""
    return sum(6 - r for r in range(i)) + (j - i)


def test_quadratic_terms_order_by_hand() -> None:
    w = np.array([1.0, 2.0, 3.0, 5.0, 7.0, 11.0])
    q = quadratic_terms(w)
    assert q.shape == (21,)
    assert q[_pair(0, 0)] == 1.0 and q[_pair(0, 2)] == 3.0 and q[_pair(2, 5)] == 33.0
    assert q[_pair(5, 5)] == 121.0


def test_fit_recovers_a_known_second_order_balance() -> None:
    rng = np.random.default_rng(4)
    K1 = np.eye(6) + 0.02 * rng.normal(size=(6, 6))
    K2 = np.zeros((6, 21))
    K2[2, _pair(0, 2)] = 0.004  # Fz picks up Fx * Fz
    K2[4, _pair(2, 2)] = -0.001  # My picks up Fz^2
    R = rng.uniform(-1, 1, size=(120, 6)) * np.array([5, 5, 10, 0.3, 0.3, 0.3])
    applied = R @ K1.T + quadratic_terms(R) @ K2.T + rng.normal(0, 1e-4, size=(120, 6))
    fit, why = fit_second_order(R, applied)
    assert fit is not None, why
    np.testing.assert_allclose(fit.K1, K1, atol=2e-3)
    assert fit.K2[2, _pair(0, 2)] == pytest.approx(0.004, rel=0.05)
    assert fit.K2[4, _pair(2, 2)] == pytest.approx(-0.001, rel=0.05)
    # on fresh loads the fitted model predicts the applied wrench to the noise level
    X = rng.uniform(-1, 1, size=(50, 6)) * np.array([5, 5, 10, 0.3, 0.3, 0.3])
    truth = X @ K1.T + quadratic_terms(X) @ K2.T
    pred, _ = apply_balance_model(X, fit.K1, fit.K2)
    assert np.abs(pred - truth).max() < 2e-3
    assert fit.rms_second[2] < 0.1 * fit.rms_first[2]


def test_fit_refuses_when_the_check_loads_cannot_carry_it() -> None:
    rng = np.random.default_rng(5)
    R = rng.normal(size=(30, 6))
    fit, why = fit_second_order(R, R)
    assert fit is None and "needs >= 54" in why
    R = rng.normal(size=(100, 6))
    fit, why = fit_second_order(R, R @ np.diag([1.01] * 6) + rng.normal(0, 1e-3, (100, 6)))
    assert fit is None and "not significant" in why
    R[:, 3] = 0.0  # Mx never loaded: its products cannot be fitted
    fit, why = fit_second_order(R, R)
    assert fit is None and "rank" in why


def test_apply_by_hand() -> None:
    K2 = np.zeros((6, 21))
    c = 0.01
    K2[2, _pair(0, 2)] = c
    W, J = apply_balance_model(np.array([[2.0, 0, 3.0, 0, 0, 0]]), np.eye(6), K2)
    assert W[0, 2] == pytest.approx(3.0 + c * 6.0)
    assert J[0, 2, 0] == pytest.approx(c * 3.0) and J[0, 2, 2] == pytest.approx(1.0 + c * 2.0)
    np.testing.assert_allclose(W[0, [0, 1, 3, 4, 5]], [2.0, 0, 0, 0, 0])
