"""Gravity, inertia and Coriolis wrenches of the platform (paper eq. 4), batched over poses.

The equation of motion (Newton-Euler) is ``A T + G + W_ext = M qdd + C`` with wrenches at P in {O}
axes and the order ``[Fx, Fy, Fz, Mx, My, Mz]``.  ``G = [m g; (R c) x m g]`` is the gravity *load*
on the platform (so ``A T0 = -G`` holds wind-off at rest) and ``M qdd + C`` the rate of change of
the platform's momentum (:func:`inertia_wrench`).  At rest this is the paper's eq. (4),
``A T = -(G + W_ext)``; the paper's sign of ``M qdd + C`` holds only there.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._checks import check_trailing
from .conventions import GRAVITY_O_MPS2
from .errors import InputError
from .rotations import angular_rates, rotation_from_euler

FloatArray = NDArray[np.float64]


def gravity_wrench(
    mass_kg: float, com_P_m: ArrayLike, R_O_P: ArrayLike, gravity_O_mps2: ArrayLike = GRAVITY_O_MPS2
) -> FloatArray:
    """Gravity load ``G = [m g; (R c) x m g]`` (..., 6) at P in {O} axes (N, N m)."""
    if not mass_kg > 0:
        raise InputError(f"mass_kg: expected > 0, got {mass_kg}")
    c = check_trailing(com_P_m, "com_P_m", (3,))
    R = check_trailing(R_O_P, "R_O_P", (3, 3))
    g = check_trailing(gravity_O_mps2, "gravity_O_mps2", (3,))
    f = mass_kg * np.broadcast_to(g, R.shape[:-2] + (3,))
    rc = np.einsum("...ij,...j->...i", R, c)
    return np.concatenate([f, np.cross(rc, f)], axis=-1)


def weight_basis(poses: ArrayLike, gravity_O_mps2: ArrayLike) -> FloatArray:
    """``B(q)`` (..., 6, 4) with ``G(q) = B(q) @ theta``, ``theta = [m, m c_x, m c_y, m c_z]``
    (kg, kg m; c in {P}), at P in {O} axes: :func:`gravity_wrench` written linear in the mass and
    its first moment, as the weight model fits them (:mod:`cdpr.analysis.weight`).

    poses: (..., 6) ``[x, y, z, roll, pitch, yaw]`` (m, rad); gravity_O_mps2: (3,).
    """
    q = check_trailing(poses, "poses", (6,))
    g = check_trailing(gravity_O_mps2, "gravity_O_mps2", (3,))
    R = rotation_from_euler(q[..., 3:])
    sk = np.array([[0.0, -g[2], g[1]], [g[2], 0.0, -g[0]], [-g[1], g[0], 0.0]])
    B = np.zeros(q.shape[:-1] + (6, 4))
    B[..., :3, 0] = g
    B[..., 3:, 1:] = -sk @ R
    return B


def finite_difference(values: ArrayLike, t_ns: ArrayLike) -> FloatArray:
    """Time derivative (n, k) of samples ``values`` (n, k) at integer-nanosecond times ``t_ns`` (n,).

    Second-order accurate central differences inside, one-sided at the ends (numpy.gradient).
    """
    v = np.asarray(values, dtype=np.float64)
    t = np.asarray(t_ns)
    if v.ndim != 2 or t.ndim != 1 or t.shape[0] != v.shape[0]:
        raise InputError(f"values (n, k) and t_ns (n,) expected, got {v.shape} and {t.shape}")
    if v.shape[0] < 3:
        raise InputError(f"finite_difference: expected at least 3 samples, got {v.shape[0]}")
    t_s = (t - t[0]).astype(np.float64) * 1e-9
    if np.any(np.diff(t_s) <= 0):
        raise InputError("t_ns: expected strictly increasing times")
    return np.gradient(v, t_s, axis=0, edge_order=2)


def inertia_wrench(
    mass_kg: float,
    com_P_m: ArrayLike,
    inertia_P_kgm2: ArrayLike,
    pose: ArrayLike,
    pose_rate: ArrayLike,
    pose_accel: ArrayLike,
) -> FloatArray:
    """Inertia plus Coriolis/centrifugal wrench ``M qdd + C`` (..., 6) at P in {O} axes.

    pose (..., 6) = [x, y, z, roll, pitch, yaw]; pose_rate and pose_accel are its first and second
    time derivatives (m/s, rad/s; m/s^2, rad/s^2).  The rigid body is referred to P: with
    ``rc = R c``, ``I_O = R I_P R^T`` (about P),

        F = m (a_P + omega_dot x rc + omega x (omega x rc))
        M = I_O omega_dot + omega x (I_O omega) + m rc x a_P

    which reduce to the paper's ``M qdd + C`` when the centre of mass is at P.  ``omega = H psi_dot``
    and the angular acceleration ``omega_dot = H psi_ddot + H_dot psi_dot``.
    """
    q = check_trailing(pose, "pose", (6,))
    qd = check_trailing(pose_rate, "pose_rate", (6,))
    qdd = check_trailing(pose_accel, "pose_accel", (6,))
    c = check_trailing(com_P_m, "com_P_m", (3,))
    I_P = check_trailing(inertia_P_kgm2, "inertia_P_kgm2", (3, 3))
    psi = q[..., 3:]
    R = rotation_from_euler(psi)
    omega, omega_dot = angular_rates(psi, qd[..., 3:], qdd[..., 3:])
    rc = np.einsum("...ij,...j->...i", R, c)
    I_O = R @ I_P @ np.swapaxes(R, -1, -2)
    a_P = qdd[..., :3]
    F = mass_kg * (a_P + np.cross(omega_dot, rc) + np.cross(omega, np.cross(omega, rc)))
    Iw = np.einsum("...ij,...j->...i", I_O, omega)
    M = (
        np.einsum("...ij,...j->...i", I_O, omega_dot)
        + np.cross(omega, Iw)
        + mass_kg * np.cross(rc, a_P)
    )
    return np.concatenate([F, M], axis=-1)


def mean_inertia_covariance(
    mass_kg: float,
    com_P_m: ArrayLike,
    inertia_P_kgm2: ArrayLike,
    pose: ArrayLike,
    pose_rate_var: ArrayLike,
    window_s: ArrayLike,
) -> FloatArray:
    """Covariance (..., 6, 6) of the mean inertia wrench over a window of ``window_s`` (...,) s of
    a platform whose pose rate has the variance ``pose_rate_var`` (..., 6) ((m/s)^2, (rad/s)^2) at
    ``pose`` (..., 6).

    The mean of ``M qdd`` over the window is ``M (v_end - v_start) / T``; with the two ends' rates
    independent (a window longer than the motion's correlation time; conservative otherwise),
    ``Cov = M diag(2 Var(v)) M^T / T^2``, M the mass matrix of :func:`inertia_wrench` (at rest:
    the Coriolis terms are second order in v)."""
    q = check_trailing(pose, "pose", (6,))
    rv = check_trailing(pose_rate_var, "pose_rate_var", (6,))
    T = np.asarray(window_s, dtype=np.float64)
    lead = q.shape[:-1]
    unit = np.broadcast_to(np.eye(6), (*lead, 6, 6))
    D = inertia_wrench(
        mass_kg, com_P_m, inertia_P_kgm2, q[..., None, :], np.zeros((*lead, 6, 6)), unit
    )  # D[..., j, :]: the wrench of a unit acceleration of coordinate j
    var_acc = 2.0 * rv / T[..., None] ** 2
    return np.asarray(np.einsum("...ji,...j,...jk->...ik", D, var_acc, D))
