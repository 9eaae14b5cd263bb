"""Tension distribution: one contract, several methods.

Every method solves ``A T = w`` for cable tensions ``T`` (..., m) within per-cable limits
``t_min_N <= T <= t_max_N`` and returns a :class:`TensionResult`.  ``A`` is the structure matrix
(..., 6, m) and ``w`` (..., 6) the wrench the cables must apply on the platform, which for a static
platform is ``w = -(G + W_ext)`` (see :mod:`cdpr.analysis.dynamics`).  All methods are batched over
the leading dimensions.

Objectives (named, because they differ):

- ``closed-form`` (Pott 2009): ``T = T_mid + A^+ (w - A T_mid)``, the min ``|T - T_mid|_2`` solution
  of the equality alone; feasible only if it happens to respect the limits.
- ``improved-closed-form`` (Pott 2014): the closed form, then clamp the worst violator at its limit,
  drop it and re-solve; approximates min ``|T - T_mid|_2`` with the limits.
- ``penalty`` (the paper): min ``|T - T_min|_2`` with the constraints as penalties, lambda schedule.
- ``exact``: the exact min ``|T - T_ref|_2`` s.t. ``A T = w`` and the limits, with ``T_ref = T_mid``
  by default; certifies infeasibility.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._checks import as_float_array, check_trailing
from .errors import InputError

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True)
class TensionResult:
    """Result of a tension distribution over a batch of poses.

    tensions_N: (..., m) cable tensions, N.
    feasible: (...,) True when ``|A T - w| <= tol`` and every tension is within its limits.
    residual_N: (...,) equilibrium residual ``|A T - w|_2`` (N and N m mixed, as the norm of the
        wrench vector).
    max_violation_N: (...,) worst bound violation ``max(t_min - T, T - t_max, 0)``, N.
    objective: the objective this method minimises, e.g. ``"min |T - T_mid|_2"``.
    method: the method's registered name.
    """

    tensions_N: FloatArray
    feasible: BoolArray
    residual_N: FloatArray
    max_violation_N: FloatArray
    objective: str
    method: str


FEASIBILITY_TOL_N = 1e-6
"""Tolerance (N) on the residual and the bounds when a result is declared feasible."""


def check_problem(
    A: ArrayLike, w: ArrayLike, t_min_N: ArrayLike, t_max_N: ArrayLike
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Validate and broadcast a tension-distribution problem.

    Returns ``A`` (..., 6, m), ``w`` (..., 6), ``t_min`` (..., m), ``t_max`` (..., m) with common
    leading dimensions.
    """
    A = as_float_array(A, "A")
    if A.ndim < 2:
        raise InputError(f"A: expected shape (..., n, m), got {A.shape}")
    n, m = A.shape[-2:]
    A = check_trailing(A, "A", (n, m))
    if m < n:
        raise InputError(f"A: expected at least as many cables as DOF (m >= n), got n={n}, m={m}")
    w = check_trailing(w, "w", (n,))
    t_min = check_trailing(t_min_N, "t_min_N", (m,))
    t_max = check_trailing(t_max_N, "t_max_N", (m,))
    if np.any(t_min >= t_max):
        raise InputError("t_min_N, t_max_N: expected t_min_N < t_max_N for every cable")
    lead = np.broadcast_shapes(A.shape[:-2], w.shape[:-1], t_min.shape[:-1], t_max.shape[:-1])
    return (
        np.broadcast_to(A, lead + (n, m)),
        np.broadcast_to(w, lead + (n,)),
        np.broadcast_to(t_min, lead + (m,)),
        np.broadcast_to(t_max, lead + (m,)),
    )


def finish(
    A: FloatArray,
    w: FloatArray,
    T: FloatArray,
    t_min: FloatArray,
    t_max: FloatArray,
    objective: str,
    method: str,
    ok: BoolArray | None = None,
) -> TensionResult:
    """Compute residual, violation and the feasible flag, and pack a :class:`TensionResult`."""
    res = np.linalg.norm(np.einsum("...ij,...j->...i", A, T) - w, axis=-1)
    viol = np.maximum(np.maximum(t_min - T, T - t_max).max(axis=-1), 0.0)
    scale = 1.0 + np.abs(t_max).max(axis=-1)
    feasible = (res <= FEASIBILITY_TOL_N * scale) & (viol <= FEASIBILITY_TOL_N * scale)
    if ok is not None:
        feasible &= ok
    return TensionResult(T, feasible, res, viol, objective, method)


def _pinv_apply(A: FloatArray, v: FloatArray) -> FloatArray:
    """``A^+ v`` (..., m) for full-row-rank ``A`` (..., n, m): ``A^T (A A^T)^-1 v``."""
    AAt = A @ np.swapaxes(A, -1, -2)
    y = np.linalg.solve(AAt, v[..., None])
    return (np.swapaxes(A, -1, -2) @ y)[..., 0]


def closed_form(
    A: ArrayLike, w: ArrayLike, t_min_N: ArrayLike, t_max_N: ArrayLike
) -> TensionResult:
    """Pott's closed form: ``T = T_mid + A^+ (w - A T_mid)``, ``T_mid = (t_min + t_max)/2``.

    The minimiser of ``|T - T_mid|_2`` subject to ``A T = w`` only; feasible when it respects limits.
    """
    A_, w_, lo, hi = check_problem(A, w, t_min_N, t_max_N)
    mid = 0.5 * (lo + hi)
    T = mid + _pinv_apply(A_, w_ - np.einsum("...ij,...j->...i", A_, mid))
    return finish(A_, w_, T, lo, hi, "min |T - T_mid|_2 (equality only)", "closed-form")


Method = Callable[[ArrayLike, ArrayLike, ArrayLike, ArrayLike], TensionResult]

METHODS: dict[str, Method] = {"closed-form": closed_form}
"""Registered tension-distribution methods by name."""


def distribute(
    method: str, A: ArrayLike, w: ArrayLike, t_min_N: ArrayLike, t_max_N: ArrayLike
) -> TensionResult:
    """Run the registered tension-distribution ``method`` (see :data:`METHODS`)."""
    try:
        fn = METHODS[method]
    except KeyError:
        raise InputError(f"method: expected one of {sorted(METHODS)}, got {method!r}") from None
    return fn(A, w, t_min_N, t_max_N)
