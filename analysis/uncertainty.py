"""First-order (linearised) covariance of the recovered external wrench.

The recovered wrench is ``W = -A(q) T - G(q)`` (absolute method) or ``W = A(q) (T0 - Tw)`` (tare
method), see :mod:`cdpr.analysis.wrench`.  Two independent error sources are propagated:

- load-cell noise: tensions with covariance ``Sigma_T`` (m, m) give ``A Sigma_T A^T`` (6, 6); in
  the tare method both ``T0`` and ``Tw`` are noisy, so ``Sigma_T = Sigma_T0 + Sigma_Tw``;
- pose noise: pose covariance ``Sigma_q`` (6, 6) (position m, Euler angles rad) gives
  ``J Sigma_q J^T`` with ``J = dW/dq`` (6, 6) evaluated by central differences (batched).

They are independent, so the total is their sum.  Units: N^2, N^2 m, N^2 m^2 blocks.  The linear
model holds when the noise is small against the curvature of ``W(q)``: for the paper's 0.5 mm and 0.1
deg on rigs of 0.5-2 m the second-order terms are below 1e-3 of the first-order ones.
Validated against a Monte Carlo run in ``tests/test_uncertainty_montecarlo.py``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._checks import as_float_array, check_trailing
from .errors import InputError
from .kinematics import structure_matrix
from .longrun import dof_of_estimate
from .rig import Rig
from .rotations import rotation_from_euler
from .wrench import recover_wrench

FloatArray = NDArray[np.float64]

POSE_STEP: tuple[float, ...] = (1e-6, 1e-6, 1e-6, 1e-6, 1e-6, 1e-6)
"""Central-difference steps for ``dW/dq`` (m, m, m, rad, rad, rad).

Central differences have truncation error ``h^2 |W'''| / 6`` and rounding error ``eps |W| / h``;
with ``W'''`` of order ``|T| / L^2`` for cable lengths ``L`` >= 0.1 m, the total is minimal near
``h = (3 eps)^(1/3) L`` ~ 1e-6 to 1e-5.  With h = 1e-6 both terms are below 1e-8 relative, far below
the 1 % a covariance needs.
"""


def _as_cov(value: ArrayLike, n: int, name: str) -> FloatArray:
    """A scalar standard deviation, an (n,) vector of standard deviations or an (..., n, n) covariance
    matrix, returned as a covariance (..., n, n)."""
    v = as_float_array(value, name)
    if not np.all(np.isfinite(v)):
        raise InputError(f"{name}: expected finite values, got NaN or inf")
    if v.ndim == 0 or v.shape == (n,):
        if np.any(v < 0):
            raise InputError(f"{name}: standard deviations must be >= 0")
        return np.diag(np.broadcast_to(v, (n,)) ** 2)
    if v.ndim >= 2 and v.shape[-2:] == (n, n):
        return v
    raise InputError(f"{name}: expected a scalar, ({n},) or (..., {n}, {n}), got {v.shape}")


def propagate(M: ArrayLike, C: ArrayLike) -> FloatArray:
    """``M C M^T`` (..., k, k): a covariance C (..., n, n) carried through a linear map M (..., k, n)
    (first order for a non-linear map with M its Jacobian)."""
    m = np.asarray(M, dtype=np.float64)
    return np.asarray(m @ np.asarray(C, dtype=np.float64) @ np.swapaxes(m, -1, -2))


def tension_noise_covariance(A: ArrayLike, tension_cov: ArrayLike) -> FloatArray:
    """``A Sigma_T A^T`` (..., 6, 6): wrench covariance from tension noise.

    A: (..., 6, m) structure matrix; tension_cov: scalar or (m,) standard deviations (N), or an
    (..., m, m) covariance (N^2).
    """
    a = as_float_array(A, "A")
    if a.ndim < 2 or a.shape[-2] != 6:
        raise InputError(f"A: expected shape (..., 6, m), got {a.shape}")
    S = _as_cov(tension_cov, a.shape[-1], "tension_cov")
    return a @ S @ np.swapaxes(a, -1, -2)


def pose_jacobian(
    wrench_of_pose: Callable[[FloatArray], FloatArray],
    poses: ArrayLike,
    step: ArrayLike = POSE_STEP,
) -> FloatArray:
    """``J = dW/dq`` (..., 6, 6) by central differences of a batched function at poses (..., 6).

    ``wrench_of_pose`` maps poses (..., 12, 6) to wrenches (..., 12, 6); it is called once with all
    twelve perturbed poses of every input pose.  ``J[..., i, k] = dW_i / dq_k``.
    """
    q = check_trailing(poses, "poses", (6,))
    h = check_trailing(step, "step", (6,))
    if np.any(h <= 0):
        raise InputError("step: expected steps > 0")
    E = np.eye(6) * h  # (6, 6): row k = step along q_k
    qp = np.concatenate([q[..., None, :] + E, q[..., None, :] - E], axis=-2)  # (..., 12, 6)
    w = np.asarray(wrench_of_pose(qp), dtype=np.float64)
    dw = (w[..., :6, :] - w[..., 6:, :]) / (2.0 * h[:, None])  # (..., k, i)
    return np.swapaxes(dw, -1, -2)


@dataclass(frozen=True)
class WrenchCovariance:
    """Wrench covariance and its parts (each (..., 6, 6), N^2 / N^2 m / N^2 m^2).

    total = from_tensions + from_pose; jacobian (..., 6, 6) is ``dW/dq``.
    """

    total: FloatArray
    from_tensions: FloatArray
    from_pose: FloatArray
    jacobian: FloatArray

    @property
    def std(self) -> FloatArray:
        """Standard deviations (..., 6) of ``[Fx, Fy, Fz, Mx, My, Mz]`` (N, N m)."""
        return np.sqrt(np.clip(np.diagonal(self.total, axis1=-2, axis2=-1), 0.0, None))


def wrench_covariance(
    rig: Rig,
    poses: ArrayLike,
    tensions_N: ArrayLike,
    tension_cov: ArrayLike,
    pose_cov: ArrayLike,
    tare_tensions_N: ArrayLike | None = None,
    tare_tension_cov: ArrayLike | None = None,
    weight_theta: ArrayLike | None = None,
) -> WrenchCovariance:
    """Covariance of the recovered ``W_ext`` at P in {O} axes, linearised at the measured values.

    poses: (..., 6) measured poses (m, rad); tensions_N: (..., m) wind-on tensions (N).
    tension_cov: scalar or (m,) standard deviations (N) or (..., m, m) covariance of Tw.
    pose_cov: scalar or (6,) standard deviations (m, m, m, rad, rad, rad) or (..., 6, 6)
        covariance of the pose.
    tare_tensions_N: (..., m) wind-off tensions for the tare method (else the absolute method);
    tare_tension_cov: their noise (default: the same as ``tension_cov``).
    weight_theta: (4,) a fitted weight ``[m, m c]`` for the absolute method (None: the rig file's),
    as in :func:`cdpr.analysis.wrench.recover_wrench`.

    In the tare method ``T0`` and ``Tw`` are taken at the same (measured) pose, so the pose error acts
    through ``A(q) (T0 - Tw)`` only.
    """
    q = check_trailing(poses, "poses", (6,))
    m = rig.n_cables
    Tw = check_trailing(tensions_N, "tensions_N", (m,))
    R = rotation_from_euler(q[..., 3:])
    A = structure_matrix(rig.anchors_O_m, rig.attach_P_m, q[..., :3], R)
    cov_T = _as_cov(tension_cov, m, "tension_cov")
    if tare_tensions_N is not None:
        T0 = check_trailing(tare_tensions_N, "tare_tensions_N", (m,))
        cov_T0 = cov_T if tare_tension_cov is None else _as_cov(tare_tension_cov, m, "tare_cov")
        cov_T = cov_T + cov_T0
        dT = T0 - Tw

        def wrench_of_pose(qp: FloatArray) -> FloatArray:
            Ap = structure_matrix(
                rig.anchors_O_m, rig.attach_P_m, qp[..., :3], rotation_from_euler(qp[..., 3:])
            )
            return np.einsum("...kij,...j->...ki", Ap, dT)

    else:

        def wrench_of_pose(qp: FloatArray) -> FloatArray:  # the recovery itself, at qp
            return recover_wrench(rig, qp, Tw[..., None, :], weight_theta=weight_theta)

    cov_from_T = A @ cov_T @ np.swapaxes(A, -1, -2)
    J = pose_jacobian(wrench_of_pose, q)
    cov_q = _as_cov(pose_cov, 6, "pose_cov")
    cov_from_q = J @ cov_q @ np.swapaxes(J, -1, -2)
    return WrenchCovariance(
        total=cov_from_T + cov_from_q, from_tensions=cov_from_T, from_pose=cov_from_q, jacobian=J
    )


# ------------------------------------------------------------------------------------------------
# random and systematic parts, effective degrees of freedom, expanded uncertainty (GUM, AIAA S-071A)
# ------------------------------------------------------------------------------------------------
RANDOM_TERMS: tuple[str, ...] = ("load_cells", "pose", "motion")
"""σ terms that change from one point to the next (their scatter is what repeat points show); every
other term (the weight model, the windage tare, calibrations, geometry, instruments) is fixed over a
run: systematic."""


def welch_satterthwaite(u2: ArrayLike, nu: ArrayLike) -> FloatArray:
    """Effective degrees of freedom ``(sum u_i^2)^2 / sum (u_i^4 / nu_i)`` of a sum of independent
    variance parts ``u2`` (..., q) with degrees of freedom ``nu`` (..., q) (inf allowed) (GUM G.4.1);
    inf when every part has infinite degrees of freedom, NaN where the total is."""
    a = np.asarray(u2, dtype=np.float64)
    n = np.broadcast_to(np.asarray(nu, dtype=np.float64), a.shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        den = np.sum(np.where(np.isinf(n) | (a == 0), 0.0, a * a / n), axis=-1)
        tot = np.sum(a, axis=-1)
        out = np.where(den > 0, tot * tot / np.where(den > 0, den, 1.0), np.inf)
    return np.asarray(np.where(np.isfinite(tot), out, np.nan))


def coverage_factor(nu: ArrayLike, level: float = 0.95) -> FloatArray:
    """Student's t factor ``k`` for a two-sided ``level`` interval at ``nu`` degrees of freedom (the
    normal's 1.96 at 95 % for inf; NaN stays NaN)."""
    from scipy.stats import t

    n = np.asarray(nu, dtype=np.float64)
    z = float(t.ppf(0.5 + level / 2.0, np.inf))
    with np.errstate(invalid="ignore"):
        k = np.where(np.isfinite(n), t.ppf(0.5 + level / 2.0, np.maximum(n, 1.0)), z)
    return np.asarray(np.where(np.isnan(n), np.nan, k))


@dataclass(frozen=True)
class ExpandedUncertainty:
    """Per point and output quantity (s, p): the random and systematic standard uncertainties, the
    effective degrees of freedom of the total, its coverage factor and the expanded uncertainty
    ``U = k u`` at the level asked; dof_random: the random part's own degrees of freedom (what a
    comparison of repeat points with the random part needs)."""

    u_random: FloatArray
    u_systematic: FloatArray
    dof: FloatArray
    k: FloatArray
    U: FloatArray
    dof_random: FloatArray


def expanded_uncertainty(
    terms: dict[str, ArrayLike],
    out_map: ArrayLike,
    load_map: ArrayLike,
    load_support: ArrayLike,
    sample_cov_N2: ArrayLike,
    cov_of_mean_N2: ArrayLike,
    n_used: ArrayLike,
    bandwidth: ArrayLike | None = None,
    extra_systematic_u2: ArrayLike | None = None,
    level: float = 0.95,
    term_dof: Mapping[str, float] | None = None,
) -> ExpandedUncertainty:
    """Random and systematic parts and the expanded uncertainty of linear outputs of the wrench.

    terms: name -> (s, 6, 6) covariance of the wrench at P in {O} from each source (the core's
    ``cov_terms``; :data:`RANDOM_TERMS` are random, the rest systematic); out_map: (s, p, 6) the
    outputs as linear maps of that wrench (the moment transfer to the MRP, the coefficient map);
    load_map (s, K, 6, m) and load_support (s, K): the load-cell part of each wrench as a map of raw
    point means (:func:`cdpr.analysis.tare.load_cell_maps`), whose sample covariances
    ``sample_cov_N2`` (S, m, m), covariances of the mean ``cov_of_mean_N2`` (S, m, m) and counts
    ``n_used`` (S,) with the estimate's Bartlett ``bandwidth`` (S,) give each raw mean's degrees of
    freedom for each output (:func:`cdpr.analysis.longrun.dof_of_estimate` with
    ``n_eff = c Gamma_0 c^T / c C c^T``); the pose and the systematic
    terms count with infinite degrees of freedom (calibrations and stated accuracies);
    extra_systematic_u2: (s, p) systematic variance not in the wrench (q and rho on the
    coefficients, :func:`cdpr.analysis.systematic.flow_coefficient_covariance`); term_dof: the
    degrees of freedom of systematic terms fitted from data (the load-cell calibration's
    ``n_points - 2``, the interaction matrix's check loads minus regressors:
    ``meta["systematic_dof"]`` of the ``systematic`` stage), each then its own part of the sum
    (terms not named: infinite).  The total's degrees of freedom by Welch-Satterthwaite, ``k`` from
    Student's t.
    """
    L = as_float_array(out_map, "out_map")
    s, p, _ = L.shape
    u2 = {
        k: np.einsum("spi,sij,spj->sp", L, np.asarray(v, dtype=np.float64), L)
        for k, v in terms.items()
    }
    zero = np.zeros((s, p))
    u_rand2 = sum((u2[k] for k in RANDOM_TERMS if k in u2), zero)
    u_sys2 = sum((u2[k] for k in u2 if k not in RANDOM_TERMS), zero)
    if extra_systematic_u2 is not None:
        u_sys2 = u_sys2 + np.asarray(extra_systematic_u2, dtype=np.float64)
    # the load cells' part, raw mean by raw mean, each with its own degrees of freedom
    G = np.einsum("spi,skim->skpm", L, as_float_array(load_map, "load_map"))
    sup = np.asarray(load_support, dtype=np.int64)
    used = (sup >= 0)[..., None]
    k_ = np.maximum(sup, 0)
    Cm = np.asarray(cov_of_mean_N2, dtype=np.float64)[k_]
    G0 = np.asarray(sample_cov_N2, dtype=np.float64)[k_]
    uk = np.where(used, np.einsum("skpm,skmn,skpn->skp", G, Cm, G), 0.0)
    gk = np.where(used, np.einsum("skpm,skmn,skpn->skp", G, G0, G), 0.0)
    nk = np.asarray(n_used, dtype=np.float64)[k_][..., None]
    Lk = 1.0 if bandwidth is None else np.asarray(bandwidth, dtype=np.float64)[k_][..., None]
    with np.errstate(divide="ignore", invalid="ignore"):
        nu_k = dof_of_estimate(np.where(uk > 0, gk / uk, nk), Lk, nk)
    u_pose2 = u2.get("pose", zero)
    u_load2 = np.sum(uk, axis=1)
    nu_load = welch_satterthwaite(np.moveaxis(uk, 1, -1), np.moveaxis(nu_k, 1, -1))
    # the systematic part term by term: a fitted calibration brings its own degrees of freedom
    tdof = dict(term_dof or {})
    fitted = [k for k in u2 if k not in RANDOM_TERMS and math.isfinite(tdof.get(k, math.inf))]
    u_sys_rest = u_sys2 - sum((u2[k] for k in fitted), zero)
    parts = np.stack(
        [u_load2, u_pose2 + (u_rand2 - u_load2 - u_pose2), u_sys_rest, *(u2[k] for k in fitted)],
        axis=-1,
    )
    nus = np.stack(
        [nu_load, *(np.full((s, p), v) for v in [np.inf, np.inf, *(tdof[k] for k in fitted)])],
        axis=-1,
    )
    dof = welch_satterthwaite(np.clip(parts, 0.0, None), nus)
    dof_random = welch_satterthwaite(np.clip(parts[..., :2], 0.0, None), nus[..., :2])
    k = coverage_factor(dof, level)
    u = np.sqrt(np.clip(u_rand2 + u_sys2, 0.0, None))
    return ExpandedUncertainty(
        np.sqrt(np.clip(u_rand2, 0.0, None)),
        np.sqrt(np.clip(u_sys2, 0.0, None)),
        dof,
        k,
        k * u,
        dof_random,
    )
