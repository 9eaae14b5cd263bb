"""The covariance of a window's mean from the data's own correlation (the random part of a point).

Consecutive samples of a balance are not independent: flow unsteadiness is correlated over tens of
milliseconds, the platform's modes ring, and a fluctuating load moves all cables together.  The
covariance of the mean of n samples is then ``Omega / n`` with ``Omega`` the *long-run* (zero-
frequency) covariance ``sum_k Gamma_k`` of the series, not ``Gamma_0 / n``.

Estimator (Andrews & Monahan 1992, "An improved heteroskedasticity and autocorrelation consistent
covariance matrix estimator", Econometrica 60(4)): **VAR prewhitening, then a Bartlett kernel on the
residuals, then recolouring**.

1. The window's deviations from its mean are fitted by a vector autoregression
   ``d_t = sum_{k=1..p} A_k d_{t-k} + u_t`` (least squares), its order p in 0..``max_order`` chosen
   by Akaike's criterion (AIC; the Bayesian criterion picks too few lags when a common load is
   seen through the cells' own noise, an ARMA process: its long-run variance came out 30 % low,
   15 % with AIC); an AR(1) captures correlated noise, an AR(2) a ringing mode.
2. The residuals' long-run covariance by the Bartlett kernel (Newey & West 1987),
   ``Omega_u = G_0 + sum_{k=1..L} (1 - k/(L+1)) (G_k + G_k^T)``, with the bandwidth of Andrews
   (1991, "Heteroskedasticity and autocorrelation consistent covariance matrix estimation",
   Econometrica 59(3), eq. 6.2 and 6.4): ``L = 1.1447 (a1 n)^(1/3)`` from AR(1) fits to each
   residual channel (``a1 = sum 4 r^2 s^4 / ((1-r)^6 (1+r)^2) / sum s^4/(1-r)^4``), and at least
   :data:`MIN_BANDWIDTH_FRACTION` of the window.
3. Recoloured: ``Omega = (I - sum A_k)^-1 Omega_u (I - sum A_k)^-T``.

Before all this a straight line in time is taken out of each channel of the window (least
squares over the usable samples; the mean itself is untouched): a linear trend inside a point, the
load cells' zero drift or a slowly settling load, makes the window's mean the value at the
window's middle, not a random error of it, yet it would weigh in the long-run sum at every lag
(the drift of 0.002 N/s typical of strain-gauge cells made the wrench's load-cell σ 1.2-1.5 times
the scatter of 3 s points).  What a line removes from a stationary process is one of its lowest
frequencies, negligible when the correlation time is well under the window (and a window that is
not is flagged ``window_too_short``).  The mean and the line taken out bias the Bartlett sum low
by a known amount (about the bandwidth over the window, twice that with the line: 5-10 % with the
floor below); the sum is divided by its exact expectation for white residuals
(:func:`_regression_bias`), so that white noise gets sd**2 / n on average.

Effective number of independent samples of a linear combination c of the channels:
``n_eff = n c^T Gamma_0 c / c^T Omega c`` (n for white noise, ``n (1 - rho)/(1 + rho)`` for an
AR(1)).  Degrees of freedom of the variance estimate (for the coverage factor of an expanded
uncertainty), :func:`dof_of_estimate`: ``nu = 1 / ((2/3) L/n + 2/n_eff)``, the Bartlett part's
relative variance (Andrews 1991) and the autoregression's (the variance of ``log Omega`` of an
AR(1) fit is about ``4 / n_eff``), a chi-square variance estimate having ``2 / nu``.

Masked samples (mask bits, NaN) are left out: the mean is over the usable samples, a lag pair
counts only when both of its samples are usable, and the VAR is fitted on the stretches where a
sample and its p predecessors are all usable.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import InputError

FloatArray = NDArray[np.float64]

MAX_ORDER: int = 8
"""The largest VAR order tried (a ringing mode needs 2; 4 leaves room for two)."""

MIN_BANDWIDTH_FRACTION: float = 0.05
"""The Bartlett bandwidth on the residuals is at least this fraction of the window: a finite VAR
leaves some correlation in the residuals when the process is not an autoregression (a common load
seen through each cell's own noise is an ARMA process), and Andrews' per-channel plug-in does not
see it along the common direction (its long-run variance came out at 0.3-0.6 of the truth with the
plug-in alone, 0.8 with this floor; the floor's own cost is in the degrees of freedom)."""

MIN_N_EFF: float = 10.0
"""Fewer effective samples than this and the window is too short for its own correlation: the
long-run estimate is not stable (flag ``window_too_short``, with the dwell time it would need)."""

NEAR_UNIT_ROOT: float = 0.999
"""A fitted VAR whose companion matrix has an eigenvalue beyond this modulus is not stationary
over the window (a drift, a ramp caught in the point): the estimate is flagged."""


@dataclass(frozen=True)
class LongRun:
    """The long-run covariance of one window.

    cov_of_mean: (m, m) covariance of the window's mean; sample_cov: (m, m) ``Gamma_0`` (the
    samples' covariance); n: usable samples; order: the VAR order chosen; bandwidth: the Bartlett
    bandwidth on the residuals (samples); stationary: False when the fitted VAR has a root at or
    beyond :data:`NEAR_UNIT_ROOT` (the estimate is then not to be trusted).
    """

    cov_of_mean: FloatArray
    sample_cov: FloatArray
    n: int
    order: int
    bandwidth: int
    stationary: bool

    def n_eff(self, c: ArrayLike | None = None) -> FloatArray:
        """Effective numbers of independent samples of the linear combinations ``c`` (k, m) of the
        channels (default: each channel), each ``n c Gamma_0 c^T / c (n cov_of_mean) c^T``."""
        C = np.eye(self.sample_cov.shape[0]) if c is None else np.atleast_2d(c)
        g0 = np.einsum("ki,ij,kj->k", C, self.sample_cov, C)
        om = np.einsum("ki,ij,kj->k", C, self.cov_of_mean, C) * self.n
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.asarray(np.where(om > 0, self.n * g0 / om, float(self.n)))

    def converged(self, min_n_eff: float = MIN_N_EFF) -> bool:
        """True when every channel has at least ``min_n_eff`` effective samples and the fit is
        stationary."""
        return bool(self.stationary and np.all(self.n_eff() >= min_n_eff))

    def dof(self, c: ArrayLike | None = None) -> FloatArray:
        """Degrees of freedom of the variance of ``c`` (see the module docstring)."""
        return dof_of_estimate(self.n_eff(c), self.bandwidth, self.n)


def dof_of_estimate(n_eff: ArrayLike, bandwidth: ArrayLike, n: ArrayLike) -> FloatArray:
    """Degrees of freedom of a long-run variance estimate: ``1 / ((2/3) L/n + 2/n_eff)``, the
    relative variance of a Bartlett estimate with bandwidth L (Andrews 1991: ``(4/3) L/n``) and of
    the autoregression's recolouring (about ``4/n_eff``), as a chi-square's ``2/nu``; at most
    ``n - 1``."""
    ne = np.asarray(n_eff, dtype=np.float64)
    nn = np.asarray(n, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        L = np.asarray(bandwidth, dtype=np.float64)
        nu = 1.0 / ((2.0 / 3.0) * L / nn + 2.0 / np.maximum(ne, 1e-9))
    return np.asarray(np.clip(nu, 1.0, np.maximum(nn - 1.0, 1.0)))


def _rows(ok: NDArray[np.bool_], p: int, start: int) -> NDArray[np.bool_]:
    """Samples t >= start whose samples t-p..t are all usable."""
    good = ok.copy()
    for k in range(1, p + 1):
        good[k:] &= ok[:-k]
    good[: max(p, start)] = False
    return good


def _lagged(
    d: FloatArray, ok: NDArray[np.bool_], p: int, start: int
) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
    """The regression of :func:`_rows`: (Y (N, m), X (N, m p), the rows used (n,))."""
    good = _rows(ok, p, start)
    t = np.flatnonzero(good)
    X = np.concatenate([d[t - k] for k in range(1, p + 1)], axis=1) if p else np.zeros((t.size, 0))
    return d[t], X, good


def _least_squares(X: FloatArray, Y: FloatArray) -> FloatArray:
    """``argmin |X B - Y|`` by the normal equations (X has few columns and many rows: a small
    solve instead of an SVD of X), falling back to ``lstsq`` when ``X^T X`` is singular."""
    try:
        return np.asarray(np.linalg.solve(X.T @ X, X.T @ Y))
    except np.linalg.LinAlgError:
        return np.asarray(np.linalg.lstsq(X, Y, rcond=None)[0])


def _autocov(u: FloatArray, ok: NDArray[np.bool_], L: int) -> FloatArray:
    """``G_k`` (L+1, m, m), ``G_k = sum_t u_t u_{t-k}^T / (pairs at lag k)`` over usable pairs."""
    n, m = u.shape
    z = np.where(ok[:, None], u, 0.0)
    size = 1 << int(np.ceil(np.log2(2 * n)))
    F = np.fft.rfft(z, size, axis=0)  # (f, m)
    cross = np.fft.irfft(F[:, :, None] * np.conj(F[:, None, :]), size, axis=0)[: L + 1]
    Fm = np.fft.rfft(ok.astype(np.float64), size)
    pairs = np.fft.irfft(Fm * np.conj(Fm), size)[: L + 1]
    pairs = np.maximum(np.rint(pairs), 1.0)
    # cross[k, i, j] = sum_t z_{t+k, i} z_{t, j}: G_k with u_t u_{t-k}^T
    return np.asarray(cross / pairs[:, None, None])


def _andrews_bandwidth(u: FloatArray, ok: NDArray[np.bool_]) -> int:
    """Andrews (1991) Bartlett bandwidth from AR(1) fits to each channel of ``u``."""
    n = int(ok.sum())
    both = ok[1:] & ok[:-1]
    a, b = u[1:][both], u[:-1][both]
    den = np.sum(b * b, axis=0)
    r = np.clip(
        np.where(den > 0, np.sum(a * b, axis=0) / np.where(den > 0, den, 1.0), 0.0), -0.97, 0.97
    )
    s2 = np.sum((a - r * b) ** 2, axis=0) / max(a.shape[0], 1)
    num = np.sum(4 * r**2 * s2**2 / ((1 - r) ** 6 * (1 + r) ** 2))
    dd = np.sum(s2**2 / (1 - r) ** 4)
    a1 = num / dd if dd > 0 else 0.0
    return int(max(1, min(n // 2, np.floor(1.1447 * (a1 * n) ** (1.0 / 3.0)))))


def _regression_bias(Q: FloatArray, ok: NDArray[np.bool_], w: FloatArray) -> float:
    """The expected Bartlett sum of white residuals after the regressors ``Q`` (n, r), orthonormal
    over the usable samples, were taken out, per unit variance: ``E[G_0] = 1 - r/n``,
    ``E[G_k] = -sum_t H_{t,t-k} / pairs_k`` with ``H = Q Q^T``.  Below 1 (a mean or a line removed
    takes the lowest frequencies with it); dividing by it makes the estimate unbiased for white
    residuals (about ``1 - b + b^2/3`` for the mean alone, b the bandwidth over n: Kiefer and
    Vogelsang 2005, Econometric Theory 21, 1130; twice that deficit with the line too)."""
    n_all, r = Q.shape
    L = w.size
    if ok.all() and r <= 2 and L < n_all:  # no gaps: the sums in closed form (no FFT)
        n = float(n_all)
        k = np.arange(1, L + 1, dtype=np.float64)
        m = n - k  # pairs at lag k
        tr_k = m / n  # the mean's column: sum_t (1/sqrt(n))^2 over the pairs
        if r == 2:  # the line's: sum_u (u - c + k)(u - c), u < m, c = (n - 1)/2, over sum (t - c)^2
            c = (n - 1.0) / 2.0
            s1 = m * (m - 1.0) / 2.0 - m * c
            s2 = (m - 1.0) * m * (2.0 * m - 1.0) / 6.0 - c * m * (m - 1.0) + m * c * c
            tr_k = tr_k + (s2 + k * s1) / (n * (n * n - 1.0) / 12.0)
        tr0 = r / n
        return float(max(1.0 - tr0 - 2.0 * (w @ (tr_k / m)), 0.5))
    GQ = _autocov(Q, ok, L)
    tr = np.trace(GQ, axis1=1, axis2=2)
    return float(max(1.0 - tr[0] - 2.0 * (w @ tr[1:]), 0.5))


def long_run(
    x: ArrayLike,
    usable: ArrayLike | None = None,
    max_order: int = MAX_ORDER,
    detrend: bool = True,
) -> LongRun:
    """The long-run covariance of the samples ``x`` (n, m) of one window (see the module docstring).

    usable: (n,) bool, the samples that count (default: the finite rows); detrend: take a straight
    line in time (sample index) out of each channel first (False: the deviations from the mean
    only, the classical estimator).  Needs at least
    ``8 * (max_order + 1) * m`` usable samples for the VAR; fewer: the order is lowered until it
    fits (order 0 is ``Gamma_0`` with the Bartlett kernel only)."""
    a = np.asarray(x, dtype=np.float64)
    if a.ndim == 1:
        a = a[:, None]
    if a.ndim != 2:
        raise InputError(f"x: expected (n, m), got {a.shape}")
    n_all, m = a.shape
    ok: NDArray[np.bool_] = np.asarray(np.isfinite(a).all(axis=1), dtype=bool)
    if usable is not None:
        u = np.asarray(usable, dtype=bool)
        if u.shape != (n_all,):
            raise InputError(f"usable: expected ({n_all},), got {u.shape}")
        ok &= u
    n = int(ok.sum())
    if n < 2:
        nan = np.full((m, m), np.nan)
        return LongRun(nan, nan, n, 0, 0, True)
    mean = a[ok].mean(axis=0)
    d = np.where(ok[:, None], a - mean, 0.0)
    # the regressors taken out, orthonormal over the usable samples (zero elsewhere): Q (n, r)
    Q = [np.where(ok, 1.0 / np.sqrt(n), 0.0)]
    if detrend and n > 2:
        k = np.arange(n_all, dtype=np.float64)
        k = np.where(ok, k - k[ok].mean(), 0.0)
        kk = float(k @ k)
        if kk > 0:
            d = d - np.outer(k, (k @ d) / kk)  # zero where not usable (k is)
            Q.append(k / np.sqrt(kk))
    g0 = d[ok].T @ d[ok] / n
    p_max = int(min(max_order, max(0, n // (8 * m) - 1)))
    # order by AIC on a common sample (t >= p_max)
    best = (np.inf, 0, np.zeros((0, m)), d)
    for p in range(p_max + 1):
        Y, X, _ = _lagged(d, ok, p, p_max)
        N = Y.shape[0]
        if N <= m * p + m:
            break
        B = _least_squares(X, Y) if p else np.zeros((0, m))
        E = Y - X @ B
        S = E.T @ E / N
        sign, logdet = np.linalg.slogdet(S)
        if sign <= 0:  # a perfect fit (a constant channel): nothing left to explain
            logdet = -np.inf
        aic = logdet + (m * m * p) * 2.0 / N
        if aic < best[0]:
            best = (aic, p, B, E)
    _, p, B, _ = best
    A = [B[k * m : (k + 1) * m].T for k in range(p)]  # d_t = sum A_k d_{t-k}
    # residuals on every usable sample with usable predecessors (others left out)
    Y, X, good = _lagged(d, ok, p, p)
    res = np.zeros_like(d)
    res[good] = Y - X @ B if p else Y
    L = max(_andrews_bandwidth(res, good), int(np.ceil(MIN_BANDWIDTH_FRACTION * n)))
    G = _autocov(res, good, L)
    w = 1.0 - np.arange(1, L + 1) / (L + 1.0)
    omega_u = G[0] + np.einsum("k,kij->ij", w, G[1:] + np.swapaxes(G[1:], 1, 2))
    omega_u = omega_u / _regression_bias(np.column_stack(Q), ok, w)
    stationary = True
    if p:
        comp = np.zeros((m * p, m * p))
        comp[:m] = np.concatenate(A, axis=1)
        comp[m:, :-m] = np.eye(m * (p - 1))
        stationary = bool(np.max(np.abs(np.linalg.eigvals(comp))) < NEAR_UNIT_ROOT)
        Minv = np.linalg.inv(np.eye(m) - np.sum(A, axis=0))
        omega = Minv @ omega_u @ Minv.T
    else:
        omega = omega_u
    omega = 0.5 * (omega + omega.T)
    return LongRun(omega / n, g0, n, p, L, stationary)


def window_long_runs(
    x: ArrayLike,
    ranges: Sequence[tuple[int, int]],
    mask_bits: ArrayLike | None = None,
    max_order: int = MAX_ORDER,
    detrend: bool = True,
) -> list[LongRun]:
    """:func:`long_run` of each ``[start, stop)`` window of the samples ``x`` (n, m), counting only
    samples whose mask bits are 0 (one estimate per test point; the loop is over points, the work
    inside vectorised over samples)."""
    a = np.asarray(x, dtype=np.float64)
    bits = np.zeros(a.shape[0], np.int64) if mask_bits is None else np.asarray(mask_bits)
    return [long_run(a[i:j], bits[i:j] == 0, max_order, detrend) for i, j in ranges]
