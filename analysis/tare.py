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
from .kinematics import structure_matrix
from .rig import Rig
from .rotations import rotation_from_euler
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
    mask; load_map (s, K, 6, m) and load_support (s, K): the wrench's load-cell part as a linear map
    of the raw point means it is made of, ``W_i = sum_k load_map[i, k] T_raw[load_support[i, k]]``
    (-1: an unused slot), so that the degrees of freedom of each raw mean can be combined later;
    deflection_O_m_rad, deflection_measured_O_m_rad: (s, 6) a tared point's pose minus its tare's,
    as used (:func:`tare_pose`) and as the camera measured it (NaN without a tare).
    """

    wrench_P_O_N_Nm: FloatArray
    tare_index: NDArray[np.int64]
    cov_load_cells: FloatArray
    cov_pose: FloatArray
    cov_weight_model: FloatArray
    flags: dict[str, NDArray[np.bool_]]
    load_map: FloatArray
    load_support: NDArray[np.int64]
    deflection_O_m_rad: FloatArray
    deflection_measured_O_m_rad: FloatArray


@dataclass(frozen=True)
class TarePose:
    """A wind-on point's pose relative to its tare's, from the camera and the stiffness model.

    pose: (k, 6) the point's pose (m, rad) = the tare's measured pose + ``delta``; delta: (k, 6) the
    fused pose difference; delta_measured, delta_predicted: (k, 6) the camera's and the stiffness
    model's; gain_measured: (k, 6, 6) ``F`` with ``delta = predicted + F (measured - predicted)``;
    cov_predicted: (k, 6, 6) the prediction's covariance; load_sensitivity: (k, 6, 6) ``S``, the
    prediction's change per unit of load (``delta_predicted = S load``); model_scale,
    model_scale_sd: the camera's factor on the model's deflections over all k points and its σ;
    model_rescaled: True when that factor is off 1 by more than ``sigma_rel`` and 3 σ (the
    predictions are then the model's times it); model_disagrees: (k,) True where the
    camera's difference and the model's disagree beyond their covariances (chi-square, 6 dof, at
    0.1 %): there the camera's difference alone is used (``gain_measured`` = I).
    """

    pose: FloatArray
    delta: FloatArray
    delta_measured: FloatArray
    delta_predicted: FloatArray
    gain_measured: FloatArray
    cov_predicted: FloatArray
    model_disagrees: NDArray[np.bool_]
    load_sensitivity: FloatArray
    model_scale: float
    model_scale_sd: float
    model_rescaled: bool


CHI2_6_999: float = 22.4577
"""The 99.9 % point of the chi-square distribution with 6 degrees of freedom."""


LOAD_STEPS: int = 200
"""At most this many fixed-point steps of the load a point adds over its tare (:func:`weight_tare`,
each step the structure matrices and stiffness of the tared points; each point stops at 1e-4 of
its deflection and keeps that pose, so its result does not depend on the other points)."""

TARE_POSE_SD_REL: float = 0.2
"""The stiffness model's relative σ for the deflection between a point and its tare
(:func:`tare_pose`): the cables' EA and the geometry known to a few per cent.  A rig whose frame,
end fittings or sag add compliance the model does not know shows it to the camera (the chi-square
check at 0.1 %): there the measured difference is used instead, flagged
``tare_pose_model_disagrees``."""


STIFFNESS_SHAPE_SD_REL: float = 0.05
"""The stiffness model's relative σ beyond its overall scale (which the run's camera data fit,
:func:`tare_pose`): the cables' EA from one to the next and the geometry, a few per cent."""


def _deflection(rig: Rig, pose: FloatArray, tensions_N: FloatArray, load: FloatArray) -> FloatArray:
    """The stiffness model's pose change (k, 6) [position m, Euler angles rad] under ``load``
    (k, 6) at P in {O}, at ``pose`` (k, 6) and ``tensions_N`` (k, m): ``x = K^-1 load``."""
    from .rotations import euler_rate_matrix
    from .stiffness import stiffness_matrix

    K = stiffness_matrix(
        rig.anchors_O_m, rig.attach_P_m, pose[:, :3], rotation_from_euler(pose[:, 3:]),
        tensions_N, rig.cable_EA_N, rig.mass_kg, rig.com_P_m, rig.gravity_O_mps2,
    ).K  # fmt: skip
    x = np.linalg.solve(K, load[..., None])[..., 0]
    dpsi = np.linalg.solve(euler_rate_matrix(pose[:, 3:]), x[:, 3:, None])[..., 0]
    return np.concatenate([x[:, :3], dpsi], axis=1)


def tare_pose(
    rig: Rig,
    pose_point: ArrayLike,
    pose_tare: ArrayLike,
    cov_point: ArrayLike,
    cov_tare: ArrayLike,
    tensions_tare_N: ArrayLike,
    load_change_N_Nm: ArrayLike,
    sigma_rel: float = TARE_POSE_SD_REL,
    load_cov: ArrayLike | None = None,
    load_pose_jacobian: ArrayLike | None = None,
    wander_cov: ArrayLike | None = None,
) -> TarePose:
    """The pose difference between a wind-on point and its wind-off tare, from what it really is.

    Between the two the winches hold the cables' lengths: the platform moves only as much as the
    added load deflects it, ``x = K^-1 dW`` (:func:`cdpr.analysis.stiffness.stiffness_matrix` at the
    tare's pose and tensions; ``x = [dp; dtheta]``, the rotation turned into Euler angles by the
    paper's H).  The camera measures the same difference with the noise of two mean poses.  The two
    are fused by their covariances (the model's: ``sigma_rel`` of the deflection, spread over every
    coordinate of its group, translation or rotation, so that no coordinate is taken as exact), so
    camera noise is not multiplied by the full tensions where the model is the more precise; where
    the camera is, the camera wins.

    pose_point, pose_tare: (k, 6) measured mean poses; cov_point, cov_tare: (k, 6, 6) their
    covariances; tensions_tare_N: (k, m); load_change_N_Nm: (k, 6) the load the point adds at P in
    {O} (its wrench against the tare's, a first estimate is enough: the deflection is linear in it);
    load_cov: (k, 6, 6) that load's covariance from the load cells and load_pose_jacobian (k, 6, 6)
    its change with the pose (None: the prediction's own noise left out of the weighting);
    wander_cov: (k, 6, 6) the platform's own motion in the point's and its tare's mean poses
    beyond the camera's noise (what the model for the mean load cannot know).
    """
    from .rotations import euler_rate_matrix
    from .stiffness import stiffness_matrix

    qi = check_trailing(pose_point, "pose_point", (6,))
    qj = check_trailing(pose_tare, "pose_tare", (6,))
    dW = check_trailing(load_change_N_Nm, "load_change_N_Nm", (6,))
    k = qi.shape[0]
    st = stiffness_matrix(
        rig.anchors_O_m,
        rig.attach_P_m,
        qj[:, :3],
        rotation_from_euler(qj[:, 3:]),
        tensions_tare_N,
        rig.cable_EA_N,
        rig.mass_kg,
        rig.com_P_m,
        rig.gravity_O_mps2,
    )
    x = np.linalg.solve(st.K, dW[..., None])[..., 0]  # (k, 6): [dp; dtheta]
    to_q = np.tile(np.eye(6), (k, 1, 1))
    to_q[:, 3:, 3:] = np.linalg.inv(euler_rate_matrix(qj[:, 3:]))  # dpsi = H^-1 dtheta
    measured = qi - qj
    S = np.asarray(cov_point, dtype=np.float64) + np.asarray(cov_tare, dtype=np.float64)
    # the model's scale over the run, from the camera (generalised least squares of the measured
    # differences on the predicted ones): a rig softer or stiffer than the model by more than
    # sigma_rel, beyond 3 sigma of the fit, has its predictions rescaled (flagged)
    scale, scale_sd = _model_scale(np.einsum("kij,kj->ki", to_q, x), measured, S)
    rescaled = bool(abs(scale - 1.0) > max(3.0 * scale_sd, sigma_rel))
    if rescaled:
        x = scale * x
    spread = np.concatenate(
        [np.repeat(np.linalg.norm(x[:, :3], axis=1)[:, None], 3, axis=1),
         np.repeat(np.linalg.norm(x[:, 3:], axis=1)[:, None], 3, axis=1)], axis=1
    )  # fmt: skip
    # the model's error: its scale, as well as the run's own fit knows it (never worse than the
    # prior sigma_rel), and its shape (cable to cable, STIFFNESS_SHAPE_SD_REL) in every direction
    scale_u = scale_sd if rescaled else sigma_rel  # (per point: not the other points' data)
    xx = x[:, :, None] * x[:, None, :]
    cov_x = scale_u**2 * xx + STIFFNESS_SHAPE_SD_REL**2 * (
        xx + np.einsum("ki,ij->kij", spread**2, np.eye(6))
    )
    cov_p = propagate(to_q, cov_x)
    predicted = np.einsum("kij,kj->ki", to_q, x)
    sens = (scale if rescaled else 1.0) * to_q @ np.linalg.inv(st.K)
    # the prediction also carries the noise of the load it is made from (the point's tensions),
    # through the fixed point: D = (I - sens J)^-1 sens (J: the load's change with the pose)
    cov_g = cov_p
    if load_cov is not None:
        D = sens
        if load_pose_jacobian is not None:
            Jl = np.asarray(load_pose_jacobian, dtype=np.float64)
            D = np.linalg.solve(np.eye(6) - sens @ Jl, sens)
        cov_g = cov_p + propagate(D, np.asarray(load_cov, dtype=np.float64))
    if wander_cov is not None:  # the platform is not where the mean load puts it
        cov_g = cov_g + np.asarray(wander_cov, dtype=np.float64)
    gain = np.swapaxes(np.linalg.solve(S + cov_g, np.swapaxes(cov_g, 1, 2)), 1, 2)  # Sp (Sm+Sp)^-1
    # the model is used only where the camera agrees with it: a rig whose controller holds the
    # pose, a frame softer than its cables, a model off by more than sigma_rel, all show as a
    # measured difference the prediction does not explain (chi-square at 0.1 %)
    r = measured - predicted
    chi2 = np.einsum("ki,ki->k", r, np.linalg.solve(S + cov_g, r[..., None])[..., 0])
    disagree = chi2 > CHI2_6_999
    gain[disagree] = np.eye(6)
    cov_p[disagree] = 0.0
    delta = predicted + np.einsum("kij,kj->ki", gain, r)
    return TarePose(
        qj + delta, delta, measured, predicted, gain, cov_p, disagree, sens, scale, scale_sd,
        rescaled,
    )  # fmt: skip


def _model_scale(
    predicted: FloatArray, measured: FloatArray, cov: FloatArray
) -> tuple[float, float]:
    """``(s, sd)``: the factor s that best maps the predicted pose differences (k, 6) on the
    measured ones with their covariances (k, 6, 6), ``min sum (m - s p)^T C^-1 (m - s p)``, and
    its standard deviation; (1, inf) when nothing is predicted."""
    C = np.asarray(cov, dtype=np.float64)
    pd: NDArray[np.bool_] = np.asarray(np.isfinite(C).all(axis=(1, 2)), dtype=bool)
    pd[pd] = (
        np.linalg.eigvalsh(C[pd]).min(axis=1) > 0
    )  # an exact pose (zero covariance) tells nothing here
    w = np.zeros_like(predicted)
    if pd.any():
        w[pd] = np.linalg.solve(C[pd], predicted[pd][..., None])[..., 0]
    ok = pd & np.isfinite(w).all(axis=1) & np.isfinite(measured).all(axis=1)
    den = float(np.sum(w[ok] * predicted[ok]))
    if not den > 0:
        return 1.0, float("inf")
    return float(np.sum(w[ok] * measured[ok]) / den), float(1.0 / np.sqrt(den))


def load_cell_maps(
    A: FloatArray, tare: NDArray[np.int64], mix: FloatArray
) -> tuple[FloatArray, NDArray[np.int64]]:
    """The load-cell part of each point's wrench as a map on the raw point means.

    A: (s, 6, m) structure matrices (NaN rows: no wrench); tare: (s,) each point's tare (-1: none);
    mix: (s, s) ``T'_i = sum_k mix[i, k] T_raw_k`` (the zero drift's combination; identity
    without one).  ``W_i = -A_i T'_i + A_j T'_j`` (j the tare), so the map on raw point k is
    ``-A_i mix[i, k] + A_j mix[j, k]``.  Returns the maps (s, K, 6, m) and the raw indices (s, K)
    (-1 where unused), K the largest number of raw means a point is made of.
    """
    s = A.shape[0]
    has = tare >= 0
    own = mix
    of_tare = np.where(has[:, None], mix[np.maximum(tare, 0)], 0.0)
    nz = (own != 0) | (of_tare != 0)
    K = int(nz.sum(axis=1).max()) if s else 0
    order = np.argsort(~nz, axis=1, kind="stable")[:, :K]
    used = np.take_along_axis(nz, order, axis=1)
    w_own = np.where(used, np.take_along_axis(own, order, axis=1), 0.0)
    w_tare = np.where(used, np.take_along_axis(of_tare, order, axis=1), 0.0)
    A0 = np.nan_to_num(A)
    A_tare = np.where(has[:, None, None], A0[np.maximum(tare, 0)], 0.0)
    G = -w_own[..., None, None] * A0[:, None] + w_tare[..., None, None] * A_tare[:, None]
    return G, np.where(used, order, -1).astype(np.int64)


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
    tension_mix: ArrayLike | None = None,
    tension_cov_raw_N2: ArrayLike | None = None,
    tare_pose_sd_rel: float | None = TARE_POSE_SD_REL,
    pose_motion_cov: ArrayLike | None = None,
) -> WeightTare:
    """Remove the weight from every point's cable load (see the module docstring).

    kind, start_ns: (s,); poses: (s, 6) mean poses (m, rad), pose_cov (s, 6, 6); tensions_N (s, m),
    tension_cov_N2 (s, m, m); weight: the fitted weight model (None: the rig file's mass and
    centre of mass with the prior spreads ``prior_mass_rel_sd`` and ``prior_com_sd_m``).

    tension_mix: (s, s) how each point's tensions combine the raw point means (the zero drift's
    ``tension_mix``; identity without one) and tension_cov_raw_N2 (s, m, m) the raw means'
    covariances (default: ``tension_cov_N2``).  tare_pose_sd_rel: the stiffness model's relative σ
    for the pose difference between a point and its tare (:func:`tare_pose`; None: the two
    measured poses as they are); pose_motion_cov: (s, 6, 6) each mean pose's own motion beyond the
    camera's noise (:func:`cdpr.analysis.point_inputs.pose_motion_covariance`; None: none).

    σ terms: ``load_cells`` (one covariance for the point, its tare and the zeros they share:
    :func:`load_cell_maps`), ``pose`` (both points' pose covariances through
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
    # a point's twin is at the pose it would have without its load: a soft rig yields tenths of a
    # degree under the wind, more than the tolerance (the stiffness model's deflection under the
    # point's own load over the weight model is taken out for the match only)
    q_match = q.copy()
    loaded = np.flatnonzero(finite & ~off)
    if loaded.size:
        W_own = recover_wrench(rig, q[loaded], T[loaded], weight_theta=theta)
        q_match[loaded] = q[loaded] - _deflection(rig, q[loaded], T[loaded], W_own)
    q_match = np.where(np.isfinite(q_match), q_match, q)
    tare = nearest_tare(q_match, off, start_ns, position_tol_m, angle_tol_rad) if s else np.zeros(0)
    tare = np.where(finite & ~off, tare, -1).astype(np.int64)

    has = tare >= 0
    j = tare[has]
    # a tared point's pose: its tare's + the difference the camera and the stiffness model agree on
    q_hat = q.copy()
    tp = None
    deflection = np.full((s, 6), np.nan)
    deflection_measured = np.full((s, 6), np.nan)
    disagrees = np.zeros(s, bool)
    rescaled = np.zeros(s, bool)
    if j.size and tare_pose_sd_rel is not None and not tare_shares_pose:
        i = np.flatnonzero(has)
        # the load the point adds, at the model's pose (never at the camera's: its noise times
        # the full tensions would be the load): from the tare's pose, then at the predicted
        # deflection, a fixed point (the cables' geometric stiffness against the whole: a
        # contraction, a few steps reach 1e-3 of the deflection)
        # (the weight's change over the deflection is second order: the rig file's weight, so that
        # a point's pose does not move with the other points' weight fit, on-line as off-line)
        W_tare = recover_wrench(rig, q[j], T[j])
        wander = None if pose_motion_cov is None else np.asarray(pose_motion_cov, np.float64)
        zero_q = np.zeros((i.size, 6, 6))
        # (a tension covariance not known yet, on-line early in a point, weighs nothing here)
        own = wrench_covariance(rig, q[j], T[i], np.nan_to_num(C_T[i], posinf=0.0), zero_q)
        of_tare = wrench_covariance(rig, q[j], T[j], np.nan_to_num(C_T[j], posinf=0.0), zero_q)
        load_cov = own.from_tensions + of_tare.from_tensions
        wander_ij = None if wander is None else wander[i] + wander[j]

        def pose_at(q_load: FloatArray) -> TarePose:
            first = recover_wrench(rig, q_load, T[i]) - W_tare
            return tare_pose(
                rig, q[i], q[j], C_q[i], C_q[j], T[j], first, tare_pose_sd_rel, load_cov,
                own.jacobian, wander_ij,
            )  # fmt: skip

        # each point iterates until its own step is small and then stays (its result must not
        # depend on when the other points of the run converge: on-line, they are fewer)
        q_i = q[j].copy()
        done = np.zeros(i.size, bool)
        for _ in range(LOAD_STEPS):
            pred = pose_at(q_i).delta_predicted
            new = q[j] + pred
            small = np.linalg.norm(new - q_i, axis=1) <= 1e-4 * np.linalg.norm(pred, axis=1) + 1e-15
            q_i = np.where(done[:, None], q_i, new)
            done |= small
            if done.all():
                break
        tp = pose_at(q_i)
        q_hat[i] = tp.pose
        deflection[i], deflection_measured[i] = tp.delta, tp.delta_measured
        disagrees[i] = tp.model_disagrees
        rescaled[i] = tp.model_rescaled
    W = np.full((s, 6), np.nan)
    c_pose = np.zeros((s, 6, 6))
    c_wm = np.zeros((s, 6, 6))
    J = np.zeros((s, 6, 6))
    idx = np.flatnonzero(finite)
    if idx.size:
        W[idx] = recover_wrench(rig, q_hat[idx], T[idx], weight_theta=theta)
        cov = wrench_covariance(rig, q_hat[idx], T[idx], C_T[idx], C_q[idx], weight_theta=theta)
        c_pose[idx], J[idx] = cov.from_pose, cov.jacobian
    B = weight_basis(q_hat, rig.gravity_O_mps2)
    c_wm[idx] = propagate(B[idx], np.broadcast_to(theta_cov, (len(idx), 4, 4)))
    # the load cells: one covariance over the raw point means the point is made of
    mix = np.eye(s) if tension_mix is None else np.asarray(tension_mix, dtype=np.float64)
    raw = C_T if tension_cov_raw_N2 is None else np.asarray(tension_cov_raw_N2, dtype=np.float64)
    A = np.full((s, 6, rig.n_cables), np.nan)
    if idx.size:
        A[idx] = structure_matrix(
            rig.anchors_O_m, rig.attach_P_m, q[idx, :3], rotation_from_euler(q[idx, 3:])
        )
    G, support = load_cell_maps(A, tare, mix)
    if tp is not None and j.size:
        # the model's deflection is a function of the load the point's own tensions make (and its
        # tare's): at the fixed point dW_i/dT = N (the plain map), N = I + J (I - F) (I - S J)^-1 S
        i = np.flatnonzero(has)
        Ji, S, F = J[i], tp.load_sensitivity, tp.gain_measured
        eye = np.eye(6)
        N = eye + Ji @ (eye - F) @ np.linalg.solve(eye - S @ Ji, S)
        G[i] = np.einsum("sab,skbm->skam", N, G[i])
    raw_k = np.where((support >= 0)[..., None, None], raw[np.maximum(support, 0)], 0.0)
    c_load = np.einsum("skam,skmn,skbn->sab", G, raw_k, G)
    c_load[~finite] = 0.0
    # tare where one matches: subtract the tare's own residual (its weight, measured)
    if j.size:
        W[has] = W[has] - W[j]
        if tare_shares_pose:  # one pose measurement for both: its error acts through J_i - J_j
            c_pose[has] = propagate(J[has] - J[j], C_q[has])
        elif tp is not None:  # q_i = q_j + F (e_i - e_j) + (I - F) e_model: see tare_pose
            Ji, Jj, F = J[has], J[j], tp.gain_measured
            eye = np.eye(6)
            c_pose[has] = (
                propagate(Ji @ (eye - F) - Jj, C_q[j])
                + propagate(Ji @ F, C_q[has])
                + propagate(Ji @ (eye - F), tp.cov_predicted)
            )
        else:
            c_pose[has] = c_pose[has] + c_pose[j]
        c_wm[has] = propagate(B[has] - B[j], np.broadcast_to(theta_cov, (j.size, 4, 4)))
    model_used = finite & ~has & ~off & (weight is not None)
    no_tare = finite & ~has & ~off & (weight is None)
    flags: dict[str, NDArray[np.bool_]] = {
        "tare": has,
        "tare_pose_model_disagrees": disagrees,
        "stiffness_model_rescaled": rescaled,
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
    return WeightTare(
        W, tare, c_load, c_pose, c_wm, flags, G, support, deflection, deflection_measured
    )
