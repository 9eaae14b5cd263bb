"""Harmonic least squares over whole cycles (cdpr.analysis.harmonics): the coefficients of known
series, the maps along a cycle against direct evaluation, and the σ against closed forms and Monte
Carlo: white noise (Var a_h = 2 σ²/n), AR(1) noise (Var a_h = 2 S(hω)/n with the AR(1) spectral
density, the mean's S(0)/n), and a noise common to two channels (their covariance)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from cdpr.analysis.harmonics import (
    cycle_index,
    grid_phases,
    harmonic_basis,
    harmonic_fit,
    harmonic_linear_map,
    harmonic_rate,
    harmonic_values,
    harmonics_from_grid,
    phase_derivative,
    phase_shift_matrix,
)

W = 2 * math.pi * 1.5  # rad/s
DT = 1e-3


def _phase(n: int, phi0: float = 0.3) -> np.ndarray:
    return W * np.arange(n) * DT + phi0


def test_noiseless_series_gives_its_coefficients() -> None:
    ph = _phase(12_000)
    coef = np.array(
        [[0.7, 1.2, -0.4, 0.05, 0.02, -0.01, 0.003], [-2.0, 0.0, 0.9, 0.0, 0.0, 0.1, 0.0]]
    )
    y = harmonic_values(coef, ph).T
    fit = harmonic_fit(ph, y, 3)
    assert fit.coef == pytest.approx(coef, abs=1e-12)
    assert fit.n_cycles == 18
    # by hand: the basis
    X = harmonic_basis(np.array([0.5]), 2)[0]
    assert X == pytest.approx([1, math.sin(0.5), math.cos(0.5), math.sin(1.0), math.cos(1.0)])


def test_grid_maps_against_direct_evaluation() -> None:
    rng = np.random.default_rng(1)
    coef = rng.normal(size=(3, 7))
    g = grid_phases(64)
    assert harmonics_from_grid(harmonic_values(coef, g).T, 3) == pytest.approx(coef.T.T, abs=1e-12)
    # shifted phase: the series at phi + d equals the shifted coefficients at phi
    d = 0.37
    phi = np.linspace(0, 7, 50)
    shifted = harmonic_values(coef @ phase_shift_matrix(d, 3).T, phi + d)
    assert shifted == pytest.approx(harmonic_values(coef, phi), abs=1e-12)
    # its derivative at d = 0, and the time derivative, by central differences
    h = 1e-6
    num = (coef @ phase_shift_matrix(h, 3).T - coef @ phase_shift_matrix(-h, 3).T) / (2 * h)
    assert phase_derivative(coef) == pytest.approx(num, abs=1e-8)
    t = np.linspace(0, 2, 40)
    dy = (harmonic_values(coef, W * (t + h)) - harmonic_values(coef, W * (t - h))) / (2 * h)
    assert harmonic_values(harmonic_rate(coef, W), W * t) == pytest.approx(dy, rel=1e-6, abs=1e-6)
    # a map that changes along the cycle: y(phi) = M(phi) x(phi), computed directly on a grid
    gg = grid_phases(128)
    M = np.stack([np.array([[1 + 0.3 * np.sin(p), 0.2 * np.cos(2 * p)], [0.1, 2.0]]) for p in gg])
    x = rng.normal(size=(2, 7)) * np.array([1, 1, 1, 0.1, 0.1, 0.01, 0.01])
    J = harmonic_linear_map(M, 3)
    y_direct = harmonics_from_grid(np.einsum("gij,jg->gi", M, harmonic_values(x, gg)), 3)
    assert (J @ x.reshape(-1)).reshape(2, 7) == pytest.approx(y_direct, abs=1e-12)


def test_cycle_index_merges_a_short_last_cycle() -> None:
    ph = np.linspace(0, 3 * 2 * math.pi + 0.1, 3001)
    c = cycle_index(ph)
    assert c.max() == 2 and c[-1] == 2  # the few samples past 3 cycles join the third


def _ar1(rng: np.random.Generator, n: int, k: int, rho: float, sd_u: float) -> np.ndarray:
    from scipy.signal import lfilter

    e = rng.normal(0.0, sd_u, (n + 500, k))
    return lfilter([1.0], [1.0, -rho], e, axis=0)[500:]


@pytest.mark.parametrize("case", ["white", "ar1"])
def test_sigma_against_closed_form_and_monte_carlo(case: str) -> None:
    """Per noise case: the claimed σ of the mean, a1, b1 and a3 (averaged over the draws) against
    the closed form (white: σ²/n and 2σ²/n; AR(1): S(λ)/n and 2 S(λ)/n with
    S(λ) = σ_u² / (1 - 2ρ cos λ + ρ²), λ = hωΔt), and the draws' own scatter against the σ
    (rms of the standardised errors near 1)."""
    rng = np.random.default_rng(7)
    n, draws = 40_000, 300  # 60 cycles at 1.5 Hz, 1 kHz
    ph = _phase(n)
    true = np.array([0.5, 0.02, -0.01, 0.0, 0.0, 0.003, 0.0])
    clean = harmonic_values(true, ph)
    rho, sd_u = (0.0, 0.05) if case == "white" else (0.95, 0.05)
    est, sds = [], []
    for _ in range(draws):
        noise = _ar1(rng, n, 1, rho, sd_u)[:, 0] if rho else rng.normal(0, sd_u, n)
        f = harmonic_fit(ph, clean + noise, 3)
        est.append(f.coef[0])
        sds.append(f.sd[0])
    est, sds = np.array(est), np.array(sds)

    def S(h: int) -> float:
        lam = h * W * DT
        return sd_u**2 / (1 - 2 * rho * math.cos(lam) + rho**2)

    want = np.array([math.sqrt(S(0) / n), *[math.sqrt(2 * S(h) / n) for h in (1, 1, 2, 2, 3, 3)]])
    for j in (0, 1, 2, 5):
        assert sds[:, j].mean() == pytest.approx(want[j], rel=0.12), j
        z = (est[:, j] - true[j]) / sds[:, j]
        assert 0.85 < math.sqrt(np.mean(z**2)) < 1.18, (j, math.sqrt(np.mean(z**2)))
    # the AR(1) case is far from white: its mean's σ is 6x the white one's
    if case == "ar1":
        assert want[0] > 6 * sd_u / math.sqrt(n) * math.sqrt(1 / (1 - rho**2))


def test_common_noise_gives_the_channels_covariance() -> None:
    """Two channels sharing an AR(1) noise: the claimed covariance of their a1 against its closed
    form (the shared part's 2 S(ω)/n)."""
    rng = np.random.default_rng(3)
    n = 40_000
    ph = _phase(n)
    covs = []
    for _ in range(60):
        common = _ar1(rng, n, 1, 0.9, 0.04)[:, 0]
        y = np.column_stack([common + rng.normal(0, 0.02, n), -common + rng.normal(0, 0.02, n)])
        f = harmonic_fit(ph, y, 2)
        p = 5
        covs.append(f.cov[1, p + 1])
    lam = W * DT
    want = -2 * (0.04**2 / (1 - 2 * 0.9 * math.cos(lam) + 0.81)) / n
    assert np.mean(covs) == pytest.approx(want, rel=0.15)
