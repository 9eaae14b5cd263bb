"""The weight tare of every test point: its own wind-off twin where there is one, else the weight
model.

Wind on, ``W = -A(q) T - G(q)`` (:func:`cdpr.analysis.wrench.recover_wrench`).  Where a wind-off
point j was taken at the same pose as point i (within tolerances; the nearest in time,
:func:`cdpr.analysis.balance.nearest_tare`), its own load stands for the weight:
``W_i = (-A_i T_i - B_i theta) - (-A_j T_j - B_j theta)``, the small pose difference between the
two carried by the weight model ``theta`` (flag ``tare``).  Elsewhere the weight model gives
``G(q_i) = B(q_i) theta`` (flag ``weight_model``).  With neither, the point gets NaN and
``no_tare`` — unless ``allow_nominal_weight`` (an explicit choice, e.g. ``cdpr wrench`` without
``--tare``): then the rig file's mass (flag ``weight_nominal``, its prior spread in σ).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._checks import check_trailing
from .balance import nearest_tare
from .conventions import WIND_OFF_KINDS
from .dynamics import weight_basis
from .rig import Rig
from .uncertainty import propagate, wrench_covariance
from .weight import WeightModel
from .wrench import recover_wrench

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class WeightTare:
    """The weight-tared wrench of every point and its covariance by source.

    wrench_P_O_N_Nm: (s, 6) at P in {O} axes (NaN where it cannot be had; on wind-off points the
    residual against the weight model, NaN without one); tare_index: (s,) the point that served as
    tare (-1: none); cov_load_cells, cov_pose, cov_weight_model: (s, 6, 6); flags: word -> (s,)
    mask.
    """

    wrench_P_O_N_Nm: FloatArray
    tare_index: NDArray[np.int64]
    cov_load_cells: FloatArray
    cov_pose: FloatArray
    cov_weight_model: FloatArray
    flags: dict[str, NDArray[np.bool_]]


def weight_tare(
    rig: Rig,
    kind: ArrayLike,
    start_ns: ArrayLike,
    poses: ArrayLike,
    pose_cov: ArrayLike,
    tensions_N: ArrayLike,
    tension_cov_N2: ArrayLike,
    weight: WeightModel | None,
    position_tol_m: float = 1e-3,
    angle_tol_rad: float = float(np.deg2rad(0.1)),
    allow_nominal_weight: bool = False,
    prior_mass_rel_sd: float = 0.05,
    prior_com_sd_m: float = 0.01,
    tare_shares_pose: bool = False,
) -> WeightTare:
    """Remove the weight from every point's cable load (see the module docstring).

    kind, start_ns: (s,); poses: (s, 6) mean poses (m, rad), pose_cov (s, 6, 6); tensions_N (s, m),
    tension_cov_N2 (s, m, m); weight: the fitted weight model (None: the rig file's mass and
    centre of mass with the prior spreads ``prior_mass_rel_sd`` and ``prior_com_sd_m``).

    σ terms: ``load_cells`` (both points), ``pose`` (both points' pose covariances through
    ``dW/dq``, independent measurements; with ``tare_shares_pose`` the tare was taken at the very
    same measured pose, as in ``cdpr wrench --tare``, and the one pose error acts through
    ``J_i - J_j``), ``weight_model`` (theta's covariance through ``B(q_i) - B(q_j)`` or ``B(q_i)``).
    """
    kind = np.asarray(kind).astype(str)
    s = kind.shape[0]
    q_in = check_trailing(poses, "poses", (6,), allow_nan=True)
    T = np.asarray(tensions_N, dtype=np.float64)
    C_q = np.asarray(pose_cov, dtype=np.float64)
    C_T = np.asarray(tension_cov_N2, dtype=np.float64)
    m0 = rig.mass_kg
    nominal = np.concatenate([[m0], m0 * rig.com_P_m])
    nominal_cov = np.diag([(prior_mass_rel_sd * m0) ** 2] + [(m0 * prior_com_sd_m) ** 2] * 3)
    theta, theta_cov = (
        (weight.theta, weight.theta_cov) if weight is not None else (nominal, nominal_cov)
    )
    finite = np.asarray(np.isfinite(T).all(axis=1) & np.isfinite(q_in).all(axis=1))
    off = np.isin(kind, WIND_OFF_KINDS) & finite
    q = np.where(finite[:, None], q_in, 0.0)
    tare = nearest_tare(q, off, start_ns, position_tol_m, angle_tol_rad) if s else np.zeros(0)
    tare = np.where(finite & ~off, tare, -1).astype(np.int64)

    W = np.full((s, 6), np.nan)
    c_load = np.zeros((s, 6, 6))
    c_pose = np.zeros((s, 6, 6))
    c_wm = np.zeros((s, 6, 6))
    J = np.zeros((s, 6, 6))
    idx = np.flatnonzero(finite)
    if idx.size:
        W[idx] = recover_wrench(rig, q[idx], T[idx], weight_theta=theta)
        cov = wrench_covariance(rig, q[idx], T[idx], C_T[idx], C_q[idx], weight_theta=theta)
        c_load[idx], c_pose[idx], J[idx] = cov.from_tensions, cov.from_pose, cov.jacobian
    B = weight_basis(q, rig.gravity_O_mps2)
    c_wm[idx] = propagate(B[idx], np.broadcast_to(theta_cov, (len(idx), 4, 4)))
    # tare where one matches: subtract the tare's own residual (its weight, measured)
    has = tare >= 0
    j = tare[has]
    if j.size:
        W[has] = W[has] - W[j]
        c_load[has] = c_load[has] + c_load[j]
        if tare_shares_pose:  # one pose measurement for both: its error acts through J_i - J_j
            c_pose[has] = propagate(J[has] - J[j], C_q[has])
        else:
            c_pose[has] = c_pose[has] + c_pose[j]
        c_wm[has] = propagate(B[has] - B[j], np.broadcast_to(theta_cov, (j.size, 4, 4)))
    model_used = finite & ~has & ~off & (weight is not None)
    no_tare = finite & ~has & ~off & (weight is None)
    flags: dict[str, NDArray[np.bool_]] = {
        "tare": has,
        "weight_model": model_used,
        "nonfinite_input": ~finite,
    }
    if weight is not None:
        for name in weight.weak:
            flags[f"weight_model_prior_{name}"] = model_used | has
    else:
        dq = np.zeros(s, bool)
        if j.size:
            dq[has] = np.any(q_in[has] != q_in[j], axis=1)
        flags["pose_diff_nominal_weight"] = dq
        if allow_nominal_weight:
            flags["weight_nominal"] = no_tare
        else:
            W[no_tare] = np.nan
            c_load[no_tare] = c_pose[no_tare] = c_wm[no_tare] = np.nan
            flags["no_tare"] = no_tare
        W[off] = np.nan  # wind-off points keep their residual only against a weight model
    return WeightTare(W, tare, c_load, c_pose, c_wm, flags)
