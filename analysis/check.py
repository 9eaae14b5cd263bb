"""The paper's check: the tensions the controller's distribution method commands for the measured
load against the tensions the load cells measured (the "about 1 N" of its wind-tunnel test)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._checks import check_trailing
from .dynamics import weight_basis
from .rig import Rig
from .tension import distribute

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class TensionCheck:
    """dT_N: (s, m) measured minus expected tension (NaN where a point has no wrench);
    max_abs_dT_N: (s,); fail: (s,) True where ``max_abs_dT_N`` exceeds the limit."""

    dT_N: FloatArray
    max_abs_dT_N: FloatArray
    fail: NDArray[np.bool_]


def tension_check(
    rig: Rig,
    structure_matrix_O: ArrayLike,
    poses: ArrayLike,
    tensions_N: ArrayLike,
    wrench_O: ArrayLike,
    weight_theta: ArrayLike | None = None,
    method: str = "exact",
    limit_N: float = 1.0,
) -> TensionCheck:
    """Measured minus expected tensions per point.

    structure_matrix_O: (s, 6, m) at the measured poses (s, 6); tensions_N: (s, m) measured;
    wrench_O: (s, 6) the recovered aerodynamic wrench at P in {O} axes; weight_theta: (4,)
    ``[m, m c]`` of the weight model (None: the rig file's).  Expected: the tensions ``method``
    (:func:`cdpr.analysis.tension.distribute`) gives for the load ``-(G + W)`` within the rig's
    limits.  Points whose wrench is not finite get NaN and never fail.
    """
    W = check_trailing(wrench_O, "wrench_O", (6,), allow_nan=True)
    T = np.asarray(tensions_N, dtype=np.float64)
    q = check_trailing(poses, "poses", (6,), allow_nan=True)
    A = np.asarray(structure_matrix_O, dtype=np.float64)
    theta = (
        np.concatenate([[rig.mass_kg], rig.mass_kg * rig.com_P_m])
        if weight_theta is None
        else check_trailing(weight_theta, "weight_theta", (4,))
    )
    ok = np.isfinite(W).all(axis=1)
    dT = np.full(T.shape, np.nan)
    if ok.any():
        G = weight_basis(q[ok], rig.gravity_O_mps2) @ theta
        exp = distribute(method, A[ok], -(G + W[ok]), rig.t_min_N, rig.t_max_N)
        dT[ok] = T[ok] - exp.tensions_N
    mx = np.where(ok, np.abs(np.nan_to_num(dT)).max(axis=1) if len(W) else 0.0, np.nan)
    return TensionCheck(dT, mx, ok & (mx > limit_N))
