"""The covariance of a window's mean from the data's own correlation, against closed forms.

Truth: the long-run covariance of the generating process, written here from its definition
(``sum_k Gamma_k``): for an AR(1) ``x_t = rho x_{t-1} + e_t`` it is ``s^2 / (1 - rho)^2``; for a
vector AR(1) ``x_t = Phi x_{t-1} + e_t`` it is ``(I - Phi)^-1 S (I - Phi)^-T``; for an AR(2) (a ringing
mode) ``s^2 / (1 - a1 - a2)^2``.  The processes are made with scipy's ``lfilter`` (a one-line
recursion), never with the code under test.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import lfilter

from cdpr.analysis.errors import InputError
from cdpr.analysis.longrun import long_run, window_long_runs

N = 2000  # 2 s at 1 kHz: a test point


def _ar1(rng: np.random.Generator, n: int, m: int, rho: float) -> np.ndarray:
    e = rng.normal(0.0, 1.0, (n + 500, m))
    return lfilter([1.0], [1.0, -rho], e, axis=0)[500:]


def _z_scores(make, truth_var: np.ndarray, windows: int = 120, seed: int = 0):
    """Standardised errors of the window means (true mean 0) and the estimated / true variance."""
    rng = np.random.default_rng(seed)
    z, ratio, lrs = [], [], []
    for _ in range(windows):
        x = make(rng)
        lr = long_run(x)
        sd = np.sqrt(np.diag(lr.cov_of_mean))
        z.append(x.mean(axis=0) / sd)
        ratio.append(np.diag(lr.cov_of_mean) * x.shape[0] / truth_var)
        lrs.append(lr)
    return np.array(z), np.array(ratio), lrs


@pytest.mark.parametrize("rho", [0.0, 0.9, 0.98])
def test_ar1_long_run_variance_and_coverage(rho: float) -> None:
    truth = 1.0 / (1.0 - rho) ** 2 * np.ones(3)
    z, ratio, lrs = _z_scores(lambda rng: _ar1(rng, N, 3, rho), truth)
    # unbiased within the spread of an estimate from ~n_eff samples
    assert abs(np.median(ratio) - 1.0) < (0.08 if rho < 0.95 else 0.15), np.median(ratio)
    rms = np.sqrt(np.mean(z**2))
    assert 0.85 < rms < 1.2, rms
    cover = np.mean(np.abs(z) <= 1.96)
    assert 0.88 <= cover <= 0.99, cover
    # effective samples: n (1 - rho) / (1 + rho) for an AR(1)
    n_eff = np.median([lr.n_eff()[0] for lr in lrs])
    assert n_eff == pytest.approx(N * (1 - rho) / (1 + rho), rel=0.3)
    if rho > 0:
        assert all(lr.order >= 1 for lr in lrs)


def test_the_naive_standard_error_is_several_times_too_small_for_correlated_noise() -> None:
    """What the issue measured: per-cell noise correlated over 30 ms at 1 kHz, sd/sqrt(n) is about
    sqrt((1 + rho)/(1 - rho)) = 7.7 times too small; the long-run estimate is not."""
    rho = float(np.exp(-1.0 / 30.0))
    rng = np.random.default_rng(3)
    zs, zl = [], []
    for _ in range(80):
        x = _ar1(rng, N, 2, rho)
        zs.append(x.mean(0) / (x.std(0, ddof=1) / np.sqrt(N)))
        zl.append(x.mean(0) / np.sqrt(np.diag(long_run(x).cov_of_mean)))
    naive, honest = np.sqrt(np.mean(np.square(zs))), np.sqrt(np.mean(np.square(zl)))
    assert 5.0 < naive < 10.0, naive
    assert 0.8 < honest < 1.25, honest


def test_common_mode_vector_ar1_gives_the_full_covariance() -> None:
    """Four channels driven by one common AR(1) load plus their own white noise: the long-run
    covariance is the full matrix (off-diagonals as large as the diagonal's common part)."""
    rho, m = 0.95, 4
    gain = np.array([1.0, -0.5, 0.8, 0.3])  # how the common load enters each channel

    def make(rng: np.random.Generator) -> np.ndarray:
        c = _ar1(rng, N, 1, rho)[:, 0]
        return c[:, None] * gain + rng.normal(0.0, 0.5, (N, m))

    truth = np.outer(gain, gain) / (1 - rho) ** 2 + np.eye(m) * 0.25
    rng = np.random.default_rng(7)
    C = np.vstack([np.eye(m), gain, [0.5, 1.0, 0.0, 0.0], rng.normal(0, 1, (4, m))])
    # the last but four cancels the common load (0.5 g1 + g2 = 0): small, and estimated so
    truth_c = np.einsum("ki,ij,kj->k", C, truth, C)
    z, ratio = [], []
    for _ in range(100):
        x = make(rng)
        lr = long_run(x)
        v = np.einsum("ki,ij,kj->k", C, lr.cov_of_mean, C)
        z.append(C @ x.mean(axis=0) / np.sqrt(v))
        ratio.append(v * N / truth_c)
    ratio_mean = np.mean(ratio, axis=0)
    assert np.all((ratio_mean > 0.8) & (ratio_mean < 1.2)), ratio_mean
    rms = np.sqrt(np.mean(np.square(z), axis=0))
    assert np.all((rms > 0.8) & (rms < 1.25)), rms


def test_a_ringing_mode_is_an_ar2_and_its_mean_is_covered() -> None:
    """A lightly damped mode at 9 Hz (the flat rig's lowest, 1 kHz samples): AR(2) poles at
    0.995 exp(+-2 pi i 9/1000); long-run variance s^2 / (1 - a1 - a2)^2."""
    r, f = 0.995, 9.0 / 1000.0
    a1, a2 = 2 * r * np.cos(2 * np.pi * f), -r * r
    truth = np.full(2, 1.0 / (1 - a1 - a2) ** 2)

    def make(rng: np.random.Generator) -> np.ndarray:
        return lfilter([1.0], [1.0, -a1, -a2], rng.normal(0, 1, (N + 1000, 2)), axis=0)[1000:]

    z, ratio, lrs = _z_scores(make, truth, windows=100, seed=4)
    assert all(lr.order >= 2 for lr in lrs)
    assert 0.8 < np.sqrt(np.mean(z**2)) < 1.25
    assert 0.88 <= np.mean(np.abs(z) <= 1.96) <= 0.99


def test_masked_samples_are_left_out_not_bridged() -> None:
    rng = np.random.default_rng(5)
    x = _ar1(rng, N, 2, 0.9)
    usable = np.ones(N, bool)
    usable[700:760] = False  # a saturated stretch
    y = x.copy()
    y[700:760] = 1e6  # garbage there must not enter
    a = long_run(y, usable)
    assert a.n == N - 60 and np.all(np.isfinite(a.cov_of_mean))
    b = long_run(x)
    # the variances agree (the independent channels' cross term is noise about 0 in both)
    np.testing.assert_allclose(
        np.diag(a.cov_of_mean) * a.n, np.diag(b.cov_of_mean) * b.n, rtol=0.25
    )
    lrs = window_long_runs(y, [(0, 1000), (1000, N)], np.where(usable, 0, 1))
    assert [lr.n for lr in lrs] == [940, 1000]


def test_a_drifting_window_has_not_converged_and_bad_shapes_raise() -> None:
    t = np.arange(N)
    rng = np.random.default_rng(6)
    x = np.column_stack([1e-3 * t + rng.normal(0, 0.01, N), rng.normal(0, 1, N)])
    x[:, 0] = np.cumsum(rng.normal(0, 1, N))  # a random walk: no stationary mean
    lr = long_run(x)
    assert not lr.converged() and lr.n_eff()[0] < 10
    assert long_run(rng.normal(0, 1, (N, 2))).converged()
    with pytest.raises(InputError, match="usable"):
        long_run(np.zeros((10, 2)), np.ones(9, bool))
    with pytest.raises(InputError, match="expected"):
        long_run(np.zeros((2, 3, 4)))


def test_a_linear_zero_drift_inside_the_window_does_not_widen_sigma() -> None:
    """A load cell's zero drift (a straight line in time) makes the window's mean the value at its
    middle, not a random error: with the line taken out, sigma is the noise's own (white here,
    sd/sqrt(n)); the classical estimator (detrend=False) counts the drift as slow noise."""
    rng = np.random.default_rng(7)
    t = np.arange(3000) * 1e-3  # a 3 s point at 1 kHz
    ratios_detrended, ratios_classical = [], []
    for _ in range(60):
        x = rng.normal(0.0, 0.05, (t.size, 2))
        x[:, 0] += 0.02 * t  # 0.02 N/s, ten times the typical strain-gauge drift
        white = 0.05 / np.sqrt(t.size)
        ratios_detrended.append(np.sqrt(long_run(x).cov_of_mean[0, 0]) / white)
        ratios_classical.append(np.sqrt(long_run(x, detrend=False).cov_of_mean[0, 0]) / white)
    assert np.median(ratios_detrended) == pytest.approx(1.0, abs=0.08)
    assert np.median(ratios_classical) > 1.3
    # masked samples are left out of the line fit too: a masked run of outliers changes nothing
    x = rng.normal(0.0, 0.05, (t.size, 2)) + 0.02 * t[:, None]
    bad = np.zeros(t.size, bool)
    bad[1000:1100] = True
    y = x.copy()
    y[bad] = 1e3
    a, b = long_run(x[~bad]), long_run(y, ~bad)
    assert np.sqrt(b.cov_of_mean[0, 0]) == pytest.approx(np.sqrt(a.cov_of_mean[0, 0]), rel=0.1)
