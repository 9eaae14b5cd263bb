"""The weight model: mass and centre of mass of everything the cables hold, fitted from wind-off tares.

Wind-off, ``A(q) T0 = -G(q)`` with the gravity load ``G = [m g; (R c) x m g]`` (see
:mod:`cdpr.analysis.dynamics`).  ``G`` is linear in ``theta = [m, m c_x, m c_y, m c_z]``
(kg, kg m; c in {P})::

    G(q) = B(q) theta,   B = [[g, 0], [0, -skew(g) R]]   (6, 4)

so a tare polar (wind-off points at several attitudes) gives theta by weighted least squares, each
point's ``-A T0`` weighted by its covariance (load-cell noise and pose noise).  The rig file's nominal
mass and centre of mass enter only as a *prior* with a stated spread: components the polar cannot
see (``c_z`` from level tares only, with gravity along z) keep the prior's spread in the covariance
and are named in :attr:`WeightModel.weak`, so the σ of what they feed stays honest.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._checks import check_trailing
from .conventions import WIND_OFF_KINDS
from .dynamics import weight_basis
from .errors import InputError
from .rig import Rig
from .uncertainty import wrench_covariance
from .wrench import recover_wrench

FloatArray = NDArray[np.float64]

THETA_NAMES: tuple[str, ...] = ("mass", "com_x", "com_y", "com_z")
"""Names of the fitted parameters (flag words use them)."""


@dataclass(frozen=True)
class WeightModel:
    """Fitted weight: mass (kg), centre of mass in {P} (m), and the covariance of
    ``theta = [m, m c_x, m c_y, m c_z]`` (4, 4) (kg^2, kg^2 m, kg^2 m^2).

    n_tares: tare points used; chi2_per_dof: weighted residual of the fit (about 1 when the noise
    model is right; NaN with no degree of freedom); weak: names of parameters the polar left
    to the prior (posterior variance above half the prior's).
    """

    theta: FloatArray
    theta_cov: FloatArray
    n_tares: int
    chi2_per_dof: float
    weak: tuple[str, ...]

    @property
    def mass_kg(self) -> float:
        return float(self.theta[0])

    @property
    def com_P_m(self) -> FloatArray:
        return np.asarray(self.theta[1:] / self.theta[0], dtype=np.float64)

    @property
    def com_sd_m(self) -> FloatArray:
        """Standard deviations of the centre of mass (3,), first order in theta."""
        m = self.theta[0]
        J = np.zeros((3, 4))
        J[:, 0] = -self.theta[1:] / m**2
        J[:, 1:] = np.eye(3) / m
        return np.asarray(np.sqrt(np.diag(J @ self.theta_cov @ J.T)), dtype=np.float64)


def fit_weight(
    poses: ArrayLike,
    minus_AT_N: ArrayLike,
    cov_N: ArrayLike,
    gravity_O_mps2: ArrayLike,
    prior_mass_kg: float,
    prior_com_P_m: ArrayLike,
    prior_mass_sd_kg: float,
    prior_com_sd_m: float,
) -> WeightModel:
    """Weighted least-squares weight model from k wind-off points.

    poses: (k, 6) tare poses; minus_AT_N: (k, 6) ``-A(q) T0`` (= G at each tare); cov_N: (k, 6, 6)
    their covariances; prior: the rig file's mass and centre of mass with standard deviations
    (``prior_com_sd_m`` per axis, applied to ``m c`` as ``m0 * sd``).
    """
    q = check_trailing(poses, "poses", (6,))
    y = check_trailing(minus_AT_N, "minus_AT_N", (6,))
    C = check_trailing(cov_N, "cov_N", (6, 6))
    if q.ndim != 2 or y.shape != q.shape or C.shape != q.shape[:1] + (6, 6):
        raise InputError(
            f"poses (k,6), minus_AT_N (k,6), cov_N (k,6,6) expected, got "
            f"{q.shape}, {y.shape}, {C.shape}"
        )
    if not (prior_mass_kg > 0 and prior_mass_sd_kg > 0 and prior_com_sd_m > 0):
        raise InputError("prior mass, its sd and the centre-of-mass sd: expected > 0")
    k = q.shape[0]
    B = weight_basis(q, gravity_O_mps2)  # (k, 6, 4)
    # regularise a singular covariance (a zero-noise component) at 1e-12 of its scale
    scale = np.maximum(np.trace(C, axis1=1, axis2=2) / 6.0, 1e-30)
    W = np.linalg.inv(C + np.eye(6) * (1e-12 * scale)[:, None, None])
    c0 = check_trailing(prior_com_P_m, "prior_com_P_m", (3,))
    theta0 = np.concatenate([[prior_mass_kg], prior_mass_kg * c0])
    P0 = np.diag([prior_mass_sd_kg**2] + [(prior_mass_kg * prior_com_sd_m) ** 2] * 3)
    info = np.einsum("kji,kjl,klm->im", B, W, B) + np.linalg.inv(P0)
    rhs = np.einsum("kji,kjl,kl->i", B, W, y) + np.linalg.solve(P0, theta0)
    cov = np.linalg.inv(info)
    theta = cov @ rhs
    r = y - np.einsum("kij,j->ki", B, theta)
    chi2 = float(np.einsum("ki,kij,kj->", r, W, r))
    dof = 6 * k - 4
    weak = tuple(n for i, n in enumerate(THETA_NAMES) if cov[i, i] > 0.5 * P0[i, i])
    if theta[0] <= 0:
        raise InputError(f"fit_weight: fitted mass {theta[0]:.4g} kg <= 0 (tares inconsistent)")
    return WeightModel(theta, 0.5 * (cov + cov.T), k, chi2 / dof if dof > 0 else float("nan"), weak)


def fit_weight_model(
    rig: Rig,
    kind: ArrayLike,
    poses: ArrayLike,
    tensions_N: ArrayLike,
    tension_cov_N2: ArrayLike,
    pose_cov: ArrayLike,
    prior_mass_rel_sd: float = 0.05,
    prior_com_sd_m: float = 0.01,
) -> WeightModel | None:
    """The weight model from a run's wind-off points, or None when it has none.

    kind: (s,) point kinds (the wind-off ones, :data:`~cdpr.analysis.conventions.WIND_OFF_KINDS`,
    with finite tensions and pose are used); poses: (s, 6) mean poses (m, rad); tensions_N: (s, m);
    tension_cov_N2: (s, m, m) and pose_cov: (s, 6, 6) the covariances of those means.  Each point's
    ``-A(q) T0`` (:func:`cdpr.analysis.wrench.recover_wrench` with a zero weight) and its
    covariance from the load cells and the pose
    (:func:`cdpr.analysis.uncertainty.wrench_covariance`) feed :func:`fit_weight`, with the rig
    file's mass and centre of mass as the prior (``prior_mass_rel_sd`` relative, ``prior_com_sd_m``
    per axis)."""
    q = check_trailing(poses, "poses", (6,), allow_nan=True)
    T = np.asarray(tensions_N, dtype=np.float64)
    off = np.isin(np.asarray(kind).astype(str), WIND_OFF_KINDS) & np.isfinite(T).all(axis=1)
    off &= np.isfinite(q).all(axis=1)
    idx = np.flatnonzero(off)
    if idx.size == 0:
        return None
    zero = np.zeros(4)
    y = recover_wrench(rig, q[idx], T[idx], weight_theta=zero)
    cov = wrench_covariance(
        rig,
        q[idx],
        T[idx],
        np.asarray(tension_cov_N2)[idx],
        np.asarray(pose_cov)[idx],
        weight_theta=zero,
    )
    return fit_weight(
        q[idx],
        y,
        cov.total,
        rig.gravity_O_mps2,
        rig.mass_kg,
        rig.com_P_m,
        prior_mass_rel_sd * rig.mass_kg,
        prior_com_sd_m,
    )


def weight_model_note(wm: WeightModel | None, rig: Rig) -> str:
    """One sentence on a fitted weight model (or its absence) for the stage log."""
    if wm is None:
        return "no wind-off point: no weight model"
    sd = wm.com_sd_m
    return (
        f"{wm.n_tares} wind-off points: mass {wm.mass_kg:.5f} ± {np.sqrt(wm.theta_cov[0, 0]):.5f} kg "
        f"(rig file {rig.mass_kg:g}); CoM_P {np.round(wm.com_P_m * 1e3, 3).tolist()} ± "
        f"{np.round(sd * 1e3, 3).tolist()} mm; chi2/dof {wm.chi2_per_dof:.3g}"
        + (f"; left to the prior: {', '.join(wm.weak)}" if wm.weak else "")
    )
