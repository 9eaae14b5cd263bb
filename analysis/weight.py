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
from .errors import InputError
from .rotations import rotation_from_euler

FloatArray = NDArray[np.float64]

THETA_NAMES: tuple[str, ...] = ("mass", "com_x", "com_y", "com_z")
"""Names of the fitted parameters (flag words use them)."""


def weight_basis(poses: ArrayLike, gravity_O_mps2: ArrayLike) -> FloatArray:
    """``B(q)`` (..., 6, 4) with ``G(q) = B(q) @ [m, m c_x, m c_y, m c_z]`` at P in {O} axes."""
    q = check_trailing(poses, "poses", (6,))
    g = check_trailing(gravity_O_mps2, "gravity_O_mps2", (3,))
    R = rotation_from_euler(q[..., 3:])
    sk = np.array([[0.0, -g[2], g[1]], [g[2], 0.0, -g[0]], [-g[1], g[0], 0.0]])
    B = np.zeros(q.shape[:-1] + (6, 4))
    B[..., :3, 0] = g
    B[..., 3:, 1:] = -sk @ R
    return B


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
