"""Calibration of the balance itself: load-cell zero and gain, and check loads on the whole rig.

Load cells: each channel reads ``counts`` for known applied tensions (dead weights through the
cable); a straight-line fit gives ``offset_counts`` and ``gain_N_per_count`` with their standard
deviations, the residuals and the non-linearity in % of the calibrated range.

Check loads: known wrenches (weights and pulleys at known points) are applied to the platform at
known poses; the wrench recovered from the measured tensions (tare method, wind-off tensions at the
same pose) is compared with the applied one.  The errors per component are the balance's
*check-load errors*; a least-squares 6x6 interaction matrix ``K`` (``W_applied ~ K W_recovered``)
corrects what the geometry model misses (anchor errors, cell cross-talk), with its residuals
reported before and after.  Pure numpy: arrays in, arrays out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cdpr.analysis.errors import InputError
from cdpr.analysis.systematic import BalanceFitCovariance, regression_fit_covariance

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class LoadCellFit:
    """Straight-line calibration of one channel: ``T_N = (counts - offset_counts) * gain``.

    offset_counts, gain_N_per_count: fitted values; sd_offset_counts, sd_gain_N_per_count: their
    standard deviations (from the residual scatter, over n_points - 2 degrees of freedom);
    residual_rms_N: RMS of the fit residual in N; nonlinearity_pct: largest |residual| in % of the
    applied load range; n_points; corr_offset_gain: the correlation of the offset's and the gain's
    errors (with the two σ, the fit's parameter covariance: what the reduction needs for the
    load-cell calibration's systematic term, :mod:`cdpr.analysis.systematic`).
    """

    offset_counts: float
    gain_N_per_count: float
    sd_offset_counts: float
    sd_gain_N_per_count: float
    residual_rms_N: float
    nonlinearity_pct: float
    n_points: int
    corr_offset_gain: float = 0.0


def fit_load_cell(load_N: ArrayLike, counts: ArrayLike) -> LoadCellFit:
    """Least-squares line through ``(counts, load_N)`` for one channel (>= 3 distinct loads).

    Fits ``load = gain * counts + c`` and returns ``offset_counts = -c / gain``.
    """
    y = np.asarray(load_N, dtype=np.float64).reshape(-1)
    x = np.asarray(counts, dtype=np.float64).reshape(-1)
    if x.shape != y.shape:
        raise InputError(f"load_N and counts: expected the same length, got {y.size} and {x.size}")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise InputError("load_N, counts: expected finite numbers")
    if np.ptp(x) == 0:
        raise InputError(
            f"counts: stuck at {x[0]:g} for every load (a dead or disconnected channel)"
        )
    if np.unique(y).size < 3:
        raise InputError(f"load_N: expected at least 3 distinct loads, got {np.unique(y).size}")
    X = np.stack([x, np.ones_like(x)], axis=1)
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    gain, c = float(coef[0]), float(coef[1])
    if gain == 0 or not np.isfinite(gain):
        raise InputError("counts: the readings do not change with the load (gain 0)")
    r = y - X @ coef
    dof = max(len(y) - 2, 1)
    s2 = float(r @ r) / dof
    cov = s2 * np.linalg.inv(X.T @ X)
    offset = -c / gain
    # offset = -c/gain: first-order propagation
    J = np.array([c / gain**2, -1.0 / gain])
    sd_off = float(np.sqrt(max(J @ cov @ J, 0.0)))
    sd_gain = float(np.sqrt(cov[0, 0]))
    c_og = float(J @ cov[:, 0])  # cov(offset, gain)
    corr = c_og / (sd_off * sd_gain) if sd_off > 0 and sd_gain > 0 else 0.0
    span = float(np.ptp(y))
    return LoadCellFit(
        offset_counts=offset,
        gain_N_per_count=gain,
        sd_offset_counts=sd_off,
        sd_gain_N_per_count=sd_gain,
        residual_rms_N=float(np.sqrt(np.mean(r**2))),
        nonlinearity_pct=float(100.0 * np.abs(r).max() / span) if span > 0 else 0.0,
        n_points=len(y),
        corr_offset_gain=float(np.clip(corr, -1.0, 1.0)),
    )


@dataclass(frozen=True)
class CheckLoadResult:
    """Check-load errors of the balance over k check loads.

    recovered: (k, 6) wrench recovered from the tensions; applied: (k, 6) the known wrench;
    error: (k, 6) recovered - applied; rms_error, max_abs_error: (6,) per component;
    interaction: (6, 6) least-squares ``K`` with ``applied ~ K recovered``;
    corrected_rms_error: (6,) RMS of ``K recovered - applied``; full_scale: (6,) the largest
    |applied| per component, to express errors in % of full scale; fit: the covariance of ``K``
    (:class:`cdpr.analysis.systematic.BalanceFitCovariance`: ``cov(K[i, j], K[k, l]) =
    residual_cov[i, k] inverse_gram[j, l]``, over k - 6 degrees of freedom; None with exactly 6
    check loads).
    """

    recovered: FloatArray
    applied: FloatArray
    error: FloatArray
    rms_error: FloatArray
    max_abs_error: FloatArray
    interaction: FloatArray
    corrected_rms_error: FloatArray
    full_scale: FloatArray
    fit: BalanceFitCovariance | None = None


def check_loads(recovered: ArrayLike, applied: ArrayLike, ridge: float = 1e-9) -> CheckLoadResult:
    """Check-load errors and the interaction matrix from recovered and applied wrenches (k, 6).

    ``K`` solves ``min sum |K w_rec - w_app|^2`` (component by component, a tiny ridge keeps it
    defined when a component is never loaded); at least 6 check loads are needed for ``K``.
    """
    R = np.asarray(recovered, dtype=np.float64)
    W = np.asarray(applied, dtype=np.float64)
    if R.ndim != 2 or R.shape[1] != 6 or R.shape != W.shape:
        raise InputError(f"recovered, applied: expected (k, 6) each, got {R.shape} and {W.shape}")
    if R.shape[0] < 6:
        raise InputError(
            f"check loads: expected at least 6 for the interaction matrix, got {R.shape[0]}"
        )
    err = R - W
    scale = np.maximum(np.abs(R).max(axis=0), 1e-12)
    Rs = R / scale
    G = Rs.T @ Rs + ridge * np.eye(6)
    K = np.linalg.solve(G, Rs.T @ W).T / scale[None, :]
    corrected = R @ K.T - W
    # the fit's covariance: a multivariate least-squares fit W = R K^T (ridge included)
    D = np.diag(1.0 / scale)
    fit = (
        regression_fit_covariance(R, corrected, np.linalg.inv(D) @ G @ np.linalg.inv(D))
        if R.shape[0] > 6
        else None
    )
    return CheckLoadResult(
        recovered=R,
        applied=W,
        error=err,
        rms_error=np.sqrt(np.mean(err**2, axis=0)),
        max_abs_error=np.abs(err).max(axis=0),
        interaction=K,
        corrected_rms_error=np.sqrt(np.mean(corrected**2, axis=0)),
        full_scale=np.abs(W).max(axis=0),
        fit=fit,
    )
