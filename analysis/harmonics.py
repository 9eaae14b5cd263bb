"""Harmonic least squares over whole cycles, with a σ that counts the residuals' correlation.

A periodic signal sampled along a forced oscillation is fitted, per channel, by

    y(t) = c0 + sum_{h=1..H} (a_h sin(h phi(t)) + b_h cos(h phi(t))) + e(t)

with ``phi(t)`` the motion's phase (rad, ``omega t`` plus a constant).  Coefficients are kept in the
order ``[c0, a1, b1, a2, b2, ...]`` (``2 H + 1`` of them, :func:`harmonic_basis`): ``a_h`` is the
part **in phase** with ``sin(h phi)`` (with the displacement, for h = 1), ``b_h`` the **quadrature**
(with the velocity).

σ (the sandwich, or HAC, covariance of least squares; Newey & West 1987): with ``G = X^T W X`` and
the scores ``z_t = w_t x_t e_t`` (x_t the regressors of sample t, w_t its weight),
``Cov(beta) = G^-1 Var(sum_t z_t) G^-1``.  ``Var(sum_t z_t)`` comes from the scores' **cycle sums**
(batch means, one batch per cycle of the motion): the long-run covariance of that short series
(:func:`cdpr.analysis.longrun.long_run`: VAR prewhitening and a Bartlett kernel, here mostly order 0
and a bandwidth of one cycle) times the number of cycles squared, scaled by ``n_c / (n_c - 1)``
(the cycle sums add up to zero by the normal equations).  Noise correlated over milliseconds to a
good part of a cycle (flow unsteadiness, ringing modes, a camera's correlated error) is counted
this way without a model of it, and the coefficients of every channel come out with their joint
covariance (channels that share noise, as the six wrench components do through the structure
matrix, keep their correlation).  Degrees of freedom: those of the long-run estimate (``n_c - 1``
for uncorrelated cycles).

On a uniform grid of one cycle, :func:`harmonics_from_grid` gives the coefficients of a function
(exact up to harmonic ``g/2 - 1``) and :func:`harmonic_values` evaluates a series: the way the
reduction carries a fitted series through a non-linear map (the body axes along the motion, a
second-order balance model) without going back to the samples.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import InputError
from .longrun import long_run

FloatArray = NDArray[np.float64]

TWO_PI = 2.0 * math.pi


def n_terms(n_harmonics: int) -> int:
    """Coefficients of a series with ``n_harmonics`` harmonics: ``2 H + 1``."""
    return 2 * int(n_harmonics) + 1


def harmonic_basis(phase_rad: ArrayLike, n_harmonics: int) -> FloatArray:
    """Regressors (..., 2H+1) ``[1, sin phi, cos phi, sin 2phi, cos 2phi, ...]`` at the phases."""
    if int(n_harmonics) < 1:
        raise InputError(f"n_harmonics: expected >= 1, got {n_harmonics}")
    ph = np.asarray(phase_rad, dtype=np.float64)
    out = np.empty(ph.shape + (n_terms(n_harmonics),))
    out[..., 0] = 1.0
    s1, c1 = np.sin(ph, out=out[..., 1]), np.cos(ph, out=out[..., 2])
    for h in range(2, int(n_harmonics) + 1):  # sin, cos of h phi by the angle sum (harmonics)
        s0, c0 = out[..., 2 * h - 3], out[..., 2 * h - 2]
        np.subtract(s0 * c1, -c0 * s1, out=out[..., 2 * h - 1])
        np.subtract(c0 * c1, s0 * s1, out=out[..., 2 * h])
    return out


def harmonic_values(coef: ArrayLike, phase_rad: ArrayLike) -> FloatArray:
    """The series of ``coef`` (..., 2H+1) at the phases (n,): values (..., n)."""
    c = np.asarray(coef, dtype=np.float64)
    H = (c.shape[-1] - 1) // 2
    if c.shape[-1] != n_terms(H):
        raise InputError(f"coef: expected 2H+1 coefficients, got {c.shape[-1]}")
    return np.asarray(np.einsum("...j,nj->...n", c, harmonic_basis(phase_rad, H)))


def harmonic_rate(coef: ArrayLike, omega_rad_s: float) -> FloatArray:
    """Coefficients of the time derivative of the series (phase ``omega t + const``):
    ``(a_h, b_h) -> (-h omega b_h, h omega a_h)``, the mean -> 0."""
    c = np.asarray(coef, dtype=np.float64)
    out = np.zeros_like(c)
    H = (c.shape[-1] - 1) // 2
    for h in range(1, H + 1):
        out[..., 2 * h - 1] = -h * omega_rad_s * c[..., 2 * h]
        out[..., 2 * h] = h * omega_rad_s * c[..., 2 * h - 1]
    return out


def phase_shift_matrix(dphi_rad: float, n_harmonics: int) -> FloatArray:
    """``S`` (2H+1, 2H+1): a series' coefficients in the phase ``phi' = phi + dphi`` are
    ``S @ coef`` (``a'_h = a_h cos h dphi + b_h sin h dphi``, ``b'_h = b_h cos h dphi -
    a_h sin h dphi``)."""
    p = n_terms(n_harmonics)
    S = np.zeros((p, p))
    S[0, 0] = 1.0
    for h in range(1, int(n_harmonics) + 1):
        c, s = math.cos(h * dphi_rad), math.sin(h * dphi_rad)
        i, j = 2 * h - 1, 2 * h
        S[i, i], S[i, j] = c, s
        S[j, i], S[j, j] = -s, c
    return S


def phase_derivative(coef: ArrayLike) -> FloatArray:
    """``d coef' / d dphi`` at ``dphi = 0`` (see :func:`phase_shift_matrix`):
    ``(a_h, b_h) -> (h b_h, -h a_h)``, the mean -> 0."""
    c = np.asarray(coef, dtype=np.float64)
    out = np.zeros_like(c)
    H = (c.shape[-1] - 1) // 2
    for h in range(1, H + 1):
        out[..., 2 * h - 1] = h * c[..., 2 * h]
        out[..., 2 * h] = -h * c[..., 2 * h - 1]
    return out


def grid_phases(n_grid: int) -> FloatArray:
    """``n_grid`` phases uniformly over one cycle, ``2 pi k / n_grid``."""
    return TWO_PI * np.arange(int(n_grid)) / int(n_grid)


def harmonics_from_grid(values: ArrayLike, n_harmonics: int) -> FloatArray:
    """Coefficients (..., 2H+1) of a function given on :func:`grid_phases` (values (g, ...)):
    the mean, ``a_h = 2/g sum f sin(h phi)``, ``b_h = 2/g sum f cos(h phi)`` (exact for a series
    of at most ``g/2 - 1`` harmonics)."""
    v = np.asarray(values, dtype=np.float64)
    g = v.shape[0]
    if g < n_terms(n_harmonics) + 1:
        raise InputError(f"values: expected at least {n_terms(n_harmonics) + 1} grid phases")
    X = harmonic_basis(grid_phases(g), n_harmonics)  # (g, p)
    scale = np.full(X.shape[1], 2.0 / g)
    scale[0] = 1.0 / g
    return np.asarray(np.einsum("g...,gj->...j", v, X) * scale)


@dataclass(frozen=True)
class HarmonicFit:
    """A harmonic least-squares fit of k channels.

    coef: (k, 2H+1) ``[c0, a1, b1, ...]`` per channel; cov: (k (2H+1), k (2H+1)) their joint
    covariance, index ``channel * (2H+1) + term``; n: samples used; n_cycles: the cycles (batches)
    the σ comes from; dof: degrees of freedom of that σ; residual_rms: (k,); omega_rad_s: carried
    for the caller (NaN when not given).
    """

    coef: FloatArray
    cov: FloatArray
    n: int
    n_cycles: int
    dof: float
    residual_rms: FloatArray

    @property
    def n_harmonics(self) -> int:
        return (self.coef.shape[1] - 1) // 2

    @property
    def sd(self) -> FloatArray:
        """(k, 2H+1) standard deviations of the coefficients."""
        return np.sqrt(np.clip(np.diag(self.cov), 0.0, None)).reshape(self.coef.shape)


def cycle_index(phase_rad: ArrayLike) -> NDArray[np.int64]:
    """The cycle (0, 1, ...) of each phase counted from the first; a last cycle shorter than half
    the others joins the one before it (a window of whole cycles that ends a sample early or late
    must not make a batch of one sample)."""
    ph = np.asarray(phase_rad, dtype=np.float64)
    if ph.size == 0:
        return np.zeros(0, np.int64)
    c = np.floor((ph - ph[0]) / TWO_PI + 1e-9).astype(np.int64)
    last = int(c[-1])
    if last >= 1:
        n_last = int(np.sum(c == last))
        n_prev = int(np.sum(c == last - 1))
        if n_last < 0.5 * n_prev:
            c[c == last] = last - 1
    return c


def harmonic_fit(
    phase_rad: ArrayLike,
    y: ArrayLike,
    n_harmonics: int = 3,
    usable: ArrayLike | None = None,
    weights: ArrayLike | None = None,
) -> HarmonicFit:
    """Least-squares harmonics of the samples ``y`` (n,) or (n, k) at the motion's phases (n,)
    (rad, increasing), with the σ of the module docstring.

    usable: (n,) bool, the samples that count (default: the finite rows); weights: (n,) or (n, k)
    per-sample weights (``1 / variance``: a weighted fit, the scores weighted alike; default 1).
    The samples should span whole cycles (the caller's window): the σ needs at least 3 cycles.
    """
    ph = np.asarray(phase_rad, dtype=np.float64).reshape(-1)
    Y = np.asarray(y, dtype=np.float64)
    if Y.ndim == 1:
        Y = Y[:, None]
    n, k = Y.shape
    if ph.shape != (n,):
        raise InputError(f"phase_rad: expected ({n},), got {ph.shape}")
    ok = np.isfinite(Y).all(axis=1) & np.isfinite(ph)
    if usable is not None:
        u = np.asarray(usable, dtype=bool)
        if u.shape != (n,):
            raise InputError(f"usable: expected ({n},), got {u.shape}")
        ok &= u
    w = None
    if weights is not None:
        w = np.asarray(weights, dtype=np.float64)
        w = np.broadcast_to(w[:, None] if w.ndim == 1 else w, (n, k))
        ok &= np.isfinite(w).all(axis=1) & (w > 0).all(axis=1)
    p = n_terms(n_harmonics)
    idx = np.flatnonzero(ok)
    if idx.size < 2 * p:
        raise InputError(f"harmonic_fit: {idx.size} usable samples, at least {2 * p} needed")
    X = harmonic_basis(ph[idx], n_harmonics)  # (N, p)
    Yu = Y[idx] if idx.size < n else Y
    Wu = None if w is None else np.ascontiguousarray(w[idx])
    coef = np.empty((k, p))
    Ginv = np.empty((k, p, p))
    if Wu is None or bool(np.all(Wu == Wu[:1])):  # each channel's weight constant
        Gi = np.linalg.inv(X.T @ X)
        coef[:] = (Gi @ (X.T @ Yu)).T
        Ginv[:] = Gi[None] / (1.0 if Wu is None else Wu[0][:, None, None])
    else:
        for c in range(k):  # channels, not samples
            Xw = X * Wu[:, c, None]
            Gi = np.linalg.inv(Xw.T @ X)
            Ginv[c] = Gi
            coef[c] = Gi @ (Xw.T @ Yu[:, c])
    E = Yu.copy()  # (N, k) the residuals, term by term (a thin product: no BLAS threads)
    for j in range(p):
        E -= X[:, j, None] * coef[None, :, j]
    WE = E if Wu is None else Wu * E
    # scores z_t = w_t x_t e_t, summed per cycle of the motion
    cyc = cycle_index(ph[idx])
    starts = np.flatnonzero(np.r_[True, np.diff(cyc) != 0])
    n_c = starts.size
    bounds = np.r_[starts, idx.size]
    S3 = np.empty((n_c, k, p))
    for c in range(n_c):  # cycles, not samples: one small product each
        a, b = bounds[c], bounds[c + 1]
        S3[c] = WE[a:b].T @ X[a:b]
    S = S3.reshape(n_c, k * p)
    if n_c < 3:
        raise InputError(f"harmonic_fit: the samples span {n_c} cycle(s), at least 3 needed")
    lr = long_run(S, max_order=1)
    V = lr.cov_of_mean * (n_c * n_c) * (n_c / (n_c - 1.0))
    B = np.zeros((k * p, k * p))
    for c in range(k):
        B[c * p : (c + 1) * p, c * p : (c + 1) * p] = Ginv[c]
    cov = B @ V @ B.T
    cov = 0.5 * (cov + cov.T)
    if lr.order == 0 and lr.bandwidth <= 1:
        dof = float(n_c - 1)
    else:
        d = lr.dof()
        d = d[np.isfinite(d)]
        dof = float(np.median(d)) if d.size else float(n_c - 1)
    rms = np.sqrt(np.mean(E * E, axis=0))
    return HarmonicFit(coef, cov, int(idx.size), int(n_c), dof, rms)


def harmonic_linear_map(maps: ArrayLike, n_harmonics: int) -> FloatArray:
    """The map of series coefficients under a linear map that changes along the cycle.

    maps: (g, r, c) a linear map ``y = M(phi) x`` at the :func:`grid_phases` of one cycle; returns
    ``J`` (r (2H+1), c (2H+1)) with ``coef_y = J coef_x`` (index ``channel * (2H+1) + term``):
    the harmonics of ``M(phi) x(phi)`` for every unit series ``x`` (exact within the series when
    the grid holds the product's harmonics)."""
    M = np.asarray(maps, dtype=np.float64)
    g, r, c = M.shape
    p = n_terms(n_harmonics)
    basis = harmonic_basis(grid_phases(g), n_harmonics)  # (g, p)
    unit = M[:, :, :, None] * basis[:, None, None, :]  # (g, r, c, p_in)
    Jm = harmonics_from_grid(unit, n_harmonics)  # (r, c, p_in, p_out)
    return np.asarray(np.moveaxis(Jm, 3, 1).reshape(r * p, c * p))
