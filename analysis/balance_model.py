"""The balance's calibration model: first-order interaction matrix, and a second-order regression
where the check loads support it (in the spirit of AIAA R-091, the balance calibration practice).

``W_applied ~ K1 W + K2 q(W)`` with ``q(W)`` the 21 products ``W_i W_j`` (i <= j, in the order of
:func:`quadratic_terms`).  The second-order terms are fitted only when the check-load set can carry
them: at least ``min_rows_per_term`` rows per unknown of a component (27), a full-rank scaled design,
and an F-test showing that the 21 extra terms lower the residual more than noise would
(``p < significance``).  Otherwise :func:`fit_second_order` says why and the first-order matrix stays the
model.  Pure numpy/scipy: arrays in, arrays out.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._checks import check_trailing
from .errors import InputError

FloatArray = NDArray[np.float64]

_I, _J = np.triu_indices(6)
N_QUADRATIC = len(_I)  # 21


def quadratic_terms(wrench: ArrayLike) -> FloatArray:
    """``q(W)`` (..., 21): the products ``W_i W_j`` for i <= j (row-major upper triangle)."""
    w = check_trailing(wrench, "wrench", (6,))
    return np.asarray(w[..., _I] * w[..., _J], dtype=np.float64)


def quadratic_jacobian(wrench: ArrayLike) -> FloatArray:
    """``dq/dW`` (..., 21, 6)."""
    w = check_trailing(wrench, "wrench", (6,))
    J = np.zeros(w.shape[:-1] + (N_QUADRATIC, 6))
    r = np.arange(N_QUADRATIC)
    J[..., r, _I] += w[..., _J]
    J[..., r, _J] += w[..., _I]
    return J


@dataclass(frozen=True)
class SecondOrderFit:
    """``W_applied ~ K1 W + K2 q(W)``: K1 (6, 6), K2 (6, 21); residual RMS per component of the
    first-order and second-order fits; the F-test p-value per component (the smallest decides);
    fit: the covariance of ``[K1 K2]`` (a :class:`cdpr.analysis.systematic.BalanceFitCovariance`
    over the 27 regressors ``[W, q(W)]``, k - 27 degrees of freedom)."""

    K1: FloatArray
    K2: FloatArray
    rms_first: FloatArray
    rms_second: FloatArray
    p_value: FloatArray
    fit: Any = None


def fit_second_order(
    recovered: ArrayLike,
    applied: ArrayLike,
    min_rows_per_term: float = 2.0,
    significance: float = 0.01,
) -> tuple[SecondOrderFit | None, str]:
    """Fit the second-order model from check loads (k, 6) each, or return None and the reason."""
    R = check_trailing(recovered, "recovered", (6,))
    W = check_trailing(applied, "applied", (6,))
    if R.ndim != 2 or R.shape != W.shape:
        raise InputError(f"recovered, applied: expected (k, 6) each, got {R.shape} and {W.shape}")
    k = R.shape[0]
    p2 = 6 + N_QUADRATIC
    need = int(np.ceil(min_rows_per_term * p2))
    if k < need:
        return None, f"{k} check loads, the second-order model needs >= {need}"
    scale = np.maximum(np.abs(R).max(axis=0), 1e-12)
    Rs = R / scale
    X1 = Rs
    X2 = np.concatenate([Rs, quadratic_terms(Rs)], axis=1)
    if np.linalg.matrix_rank(X2, tol=1e-8 * np.linalg.norm(X2, 2)) < p2:
        return None, "the check loads do not excite every product of components (rank deficient)"
    B1, *_ = np.linalg.lstsq(X1, W, rcond=None)
    B2, *_ = np.linalg.lstsq(X2, W, rcond=None)
    r1 = W - X1 @ B1
    r2 = W - X2 @ B2
    ss1, ss2 = (r1**2).sum(axis=0), (r2**2).sum(axis=0)
    dof2 = k - p2
    with np.errstate(divide="ignore", invalid="ignore"):
        F = ((ss1 - ss2) / N_QUADRATIC) / (ss2 / dof2)
    from scipy import stats  # here: importing scipy.stats costs ~2 s at every CLI start

    p = np.where(np.isfinite(F), stats.f.sf(F, N_QUADRATIC, dof2), 0.0)
    if float(p.min()) >= significance:
        return None, f"the second-order terms are not significant (smallest p = {p.min():.3g})"
    # back to unscaled wrenches: Rs = R / s, q(Rs) = q(R) / (s_i s_j)
    K1 = (B2[:6] / scale[:, None]).T
    K2 = (B2[6:] / (scale[_I] * scale[_J])[:, None]).T
    from .systematic import BalanceFitCovariance  # here: systematic imports this module

    E = np.concatenate([scale, scale[_I] * scale[_J]])  # X2 = [R, q(R)] / E, column-wise
    M = np.linalg.pinv(X2.T @ X2) / np.outer(E, E)
    cov = BalanceFitCovariance(r2.T @ r2 / dof2, 0.5 * (M + M.T), float(dof2))
    fit = SecondOrderFit(
        K1, K2, np.sqrt(ss1 / k), np.sqrt(ss2 / k), np.asarray(p, dtype=np.float64), cov
    )
    return fit, f"second order fitted from {k} check loads (smallest p = {p.min():.3g})"


def apply_balance_model(
    wrench: ArrayLike, K1: ArrayLike, K2: ArrayLike | None = None
) -> tuple[FloatArray, FloatArray]:
    """``W' = K1 W [+ K2 q(W)]`` (s, 6) and the linearised map ``J = K1 [+ K2 dq/dW]`` (s, 6, 6)
    that carries covariances (``J C J^T``)."""
    w = np.asarray(wrench, dtype=np.float64)
    k1 = np.asarray(K1, dtype=np.float64)
    if k1.shape != (6, 6) or w.ndim != 2 or w.shape[1] != 6:
        raise InputError(f"K1 (6, 6) and wrench (s, 6) expected, got {k1.shape}, {w.shape}")
    out = w @ k1.T
    J = np.broadcast_to(k1, (w.shape[0], 6, 6)).copy()
    if K2 is not None:
        k2 = np.asarray(K2, dtype=np.float64)
        if k2.shape != (6, N_QUADRATIC):
            raise InputError(f"K2: expected (6, {N_QUADRATIC}), got {k2.shape}")
        wz = np.nan_to_num(w)
        out = out + quadratic_terms(wz) @ k2.T
        J = J + k2 @ quadratic_jacobian(wz)
    return out, J
