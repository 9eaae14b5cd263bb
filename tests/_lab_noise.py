"""The lab generator's noise processes and their closed forms (numpy/scipy only).

All processes are stationary from their first sample and zero-mean; ``dt`` is the sample period.

- white: independent N(0, sd^2) per sample and channel;
- AR(1): ``x_k = rho x_(k-1) + sqrt(1 - rho^2) sd e_k``, ``rho = exp(-dt/tau)``; autocorrelation
  ``rho^|h|``, long-run variance (the spectral density at zero, the variance of a long window's
  mean times n) ``sd^2 (1 + rho)/(1 - rho)``; the exact variance of an n-sample mean is
  :func:`ar1_var_of_mean`;
- vector AR(1): the same with a covariance ``S`` between channels (``sqrt(1 - rho^2) L e_k``,
  ``L L^T = S``): long-run covariance ``S (1 + rho)/(1 - rho)``;
- narrow band: ``x_k = Re(z_k exp(i theta k))``, ``theta = 2 pi f0 dt``, with ``z`` a circular
  complex AR(1) envelope, ``rho = exp(-pi f0 dt / Q)`` (half-power bandwidth f0/Q): autocorrelation
  ``rho^|h| cos(theta h)``, long-run variance ``sd^2 (1 - rho^2)/(1 - 2 rho cos(theta) + rho^2)``.
"""

from __future__ import annotations

import numpy as np
import scipy.signal


def ar1_rho(tau_s: np.ndarray | float, dt_s: float) -> np.ndarray:
    return np.exp(-dt_s / np.asarray(tau_s, float))


def white(rng: np.random.Generator, n: int, m: int, sd: float | np.ndarray) -> np.ndarray:
    return rng.standard_normal((n, m)) * np.asarray(sd, float)


def ar1(
    rng: np.random.Generator, n: int, sd: np.ndarray, tau_s: np.ndarray, dt_s: float
) -> np.ndarray:
    """Independent AR(1) channels (n, m): per-channel sd (m,) and correlation time tau_s (m,)."""
    sd = np.atleast_1d(np.asarray(sd, float))
    rho = np.atleast_1d(ar1_rho(tau_s, dt_s))
    m = max(len(sd), len(rho))
    sd, rho = np.broadcast_to(sd, (m,)), np.broadcast_to(rho, (m,))
    e = rng.standard_normal((n, m))
    x0 = rng.standard_normal(m)
    out = np.empty((n, m))
    for j in range(m):  # one filter per channel (m = 8), vectorised over the samples
        y, _ = scipy.signal.lfilter(
            [np.sqrt(1 - rho[j] ** 2)], [1.0, -rho[j]], e[:, j], zi=[rho[j] * x0[j]]
        )
        out[:, j] = sd[j] * y
    return out


def vector_ar1(
    rng: np.random.Generator, n: int, cov: np.ndarray, tau_s: float, dt_s: float
) -> np.ndarray:
    """A d-channel AR(1) (n, d) with stationary covariance ``cov`` (d, d), one correlation time."""
    L = np.linalg.cholesky(np.asarray(cov, float))
    d = L.shape[0]
    x = ar1(rng, n, np.ones(d), np.full(d, tau_s), dt_s)  # independent unit channels
    return x @ L.T


def narrowband(
    rng: np.random.Generator, n: int, f0_Hz: float, Q: float, dt_s: float, sd: float = 1.0
) -> np.ndarray:
    """A narrow-band process (n,) around f0 (Hz) of quality Q, variance sd^2 (module docstring)."""
    rho = float(np.exp(-np.pi * f0_Hz * dt_s / Q))
    e = (rng.standard_normal(n) + 1j * rng.standard_normal(n)) / np.sqrt(2)
    z0 = (rng.standard_normal() + 1j * rng.standard_normal()) / np.sqrt(2)
    z, _ = scipy.signal.lfilter([np.sqrt(1 - rho**2)], [1.0, -rho], e, zi=[rho * z0])
    k = np.arange(n)
    return sd * np.sqrt(2) * np.real(z * np.exp(2j * np.pi * f0_Hz * dt_s * k))


def narrowband_rho(f0_Hz: float, Q: float, dt_s: float) -> float:
    return float(np.exp(-np.pi * f0_Hz * dt_s / Q))


def ar1_long_run_variance(sd: float, rho: float) -> float:
    """``sd^2 (1 + rho)/(1 - rho)``: n times the variance of a long window's mean."""
    return sd**2 * (1 + rho) / (1 - rho)


def ar1_var_of_mean(sd: float, rho: float, n: int) -> float:
    """Exact variance of the mean of n consecutive AR(1) samples:
    ``sd^2/n^2 [n + 2 sum_{k=1}^{n-1} (n-k) rho^k]``."""
    s = rho * (n * (1 - rho) - (1 - rho**n)) / (1 - rho) ** 2
    return sd**2 * (n + 2 * s) / n**2


def narrowband_long_run_variance(sd: float, rho: float, theta: float) -> float:
    """``sd^2 (1 - rho^2)/(1 - 2 rho cos(theta) + rho^2)``, ``theta = 2 pi f0 dt``."""
    return sd**2 * (1 - rho**2) / (1 - 2 * rho * np.cos(theta) + rho**2)


def var_of_mean(autocovariance: np.ndarray, n: int) -> float:
    """Exact variance of the mean of n consecutive samples of a stationary process with
    autocovariance ``gamma(h)`` (``autocovariance[h]``, h = 0 .. n-1):
    ``(1/n^2) [n gamma(0) + 2 sum_{h>=1} (n - h) gamma(h)]``."""
    g = np.asarray(autocovariance, float)[:n]
    h = np.arange(1, len(g))
    return float((n * g[0] + 2 * np.sum((n - h) * g[1:])) / n**2)
