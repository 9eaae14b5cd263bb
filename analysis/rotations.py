"""Rotations: Z-Y-X Euler angles, rotation matrices, quaternions and the Euler-rate matrix H.

All functions are batched over leading ``...`` dimensions.  Euler angles ``psi = (roll, pitch, yaw)``
in rad: roll about x, pitch about y, yaw about z, ``R_O_P = Rz(yaw) Ry(pitch) Rx(roll)`` maps {P}
components to {O} components (the paper's alpha, beta, gamma).  Quaternions are ``[w, x, y, z]``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._checks import check_trailing

FloatArray = NDArray[np.float64]


def rotation_from_euler(psi_rad: ArrayLike) -> FloatArray:
    """Rotation matrix ``R_O_P`` (..., 3, 3) from Z-Y-X Euler angles ``psi_rad`` (..., 3)."""
    psi = check_trailing(psi_rad, "psi_rad", (3,))
    ca, cb, cg = np.cos(psi[..., 0]), np.cos(psi[..., 1]), np.cos(psi[..., 2])
    sa, sb, sg = np.sin(psi[..., 0]), np.sin(psi[..., 1]), np.sin(psi[..., 2])
    R = np.empty(psi.shape[:-1] + (3, 3))
    R[..., 0, 0] = cg * cb
    R[..., 0, 1] = cg * sb * sa - sg * ca
    R[..., 0, 2] = cg * sb * ca + sg * sa
    R[..., 1, 0] = sg * cb
    R[..., 1, 1] = sg * sb * sa + cg * ca
    R[..., 1, 2] = sg * sb * ca - cg * sa
    R[..., 2, 0] = -sb
    R[..., 2, 1] = cb * sa
    R[..., 2, 2] = cb * ca
    return R


def euler_from_rotation(R_O_P: ArrayLike) -> FloatArray:
    """Z-Y-X Euler angles (..., 3) in rad from rotation matrices (..., 3, 3).

    pitch is in [-pi/2, pi/2]; at gimbal lock (|pitch| = pi/2) roll is set to 0.
    """
    R = check_trailing(R_O_P, "R_O_P", (3, 3))
    pitch = np.arctan2(-R[..., 2, 0], np.hypot(R[..., 0, 0], R[..., 1, 0]))
    lock = np.hypot(R[..., 0, 0], R[..., 1, 0]) < 1e-12
    roll = np.where(lock, 0.0, np.arctan2(R[..., 2, 1], R[..., 2, 2]))
    yaw = np.where(
        lock,
        np.arctan2(-R[..., 0, 1], R[..., 1, 1]),
        np.arctan2(R[..., 1, 0], R[..., 0, 0]),
    )
    return np.stack([roll, pitch, yaw], axis=-1)


def quaternion_from_rotation(R_O_P: ArrayLike) -> FloatArray:
    """Unit quaternions ``[w, x, y, z]`` (..., 4) with ``w >= 0`` from rotation matrices (..., 3, 3)."""
    R = check_trailing(R_O_P, "R_O_P", (3, 3))
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    # Shepperd: 4*q_k^2 for the four candidates; pick the largest for stability.
    cand = np.stack(
        [1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22],
        axis=-1,
    )
    k = np.argmax(cand, axis=-1)
    s = 2.0 * np.sqrt(np.maximum(np.take_along_axis(cand, k[..., None], -1)[..., 0], 1e-300))
    d21 = R[..., 2, 1] - R[..., 1, 2]
    d02 = R[..., 0, 2] - R[..., 2, 0]
    d10 = R[..., 1, 0] - R[..., 0, 1]
    s21 = R[..., 2, 1] + R[..., 1, 2]
    s02 = R[..., 0, 2] + R[..., 2, 0]
    s10 = R[..., 1, 0] + R[..., 0, 1]
    q = np.empty(R.shape[:-2] + (4,))
    sel = [k == i for i in range(4)]
    q[..., 0] = np.select(sel, [s / 4, d21 / s, d02 / s, d10 / s])
    q[..., 1] = np.select(sel, [d21 / s, s / 4, s10 / s, s02 / s])
    q[..., 2] = np.select(sel, [d02 / s, s10 / s, s / 4, s21 / s])
    q[..., 3] = np.select(sel, [d10 / s, s02 / s, s21 / s, s / 4])
    q *= np.where(q[..., :1] < 0, -1.0, 1.0)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def rotation_from_quaternion(q_wxyz: ArrayLike) -> FloatArray:
    """Rotation matrices (..., 3, 3) from quaternions ``[w, x, y, z]`` (..., 4); normalises first."""
    q = check_trailing(q_wxyz, "q_wxyz", (4,))
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(n < 1e-12):
        from .errors import InputError

        raise InputError("q_wxyz: expected non-zero quaternions, got a zero-norm quaternion")
    w, x, y, z = np.moveaxis(q / n, -1, 0)
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - w * z)
    R[..., 0, 2] = 2 * (x * z + w * y)
    R[..., 1, 0] = 2 * (x * y + w * z)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - w * x)
    R[..., 2, 0] = 2 * (x * z - w * y)
    R[..., 2, 1] = 2 * (y * z + w * x)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def quaternion_from_euler(psi_rad: ArrayLike) -> FloatArray:
    """Quaternions ``[w, x, y, z]`` (..., 4) from Z-Y-X Euler angles (..., 3)."""
    return quaternion_from_rotation(rotation_from_euler(psi_rad))


def euler_from_quaternion(q_wxyz: ArrayLike) -> FloatArray:
    """Z-Y-X Euler angles (..., 3) from quaternions ``[w, x, y, z]`` (..., 4)."""
    return euler_from_rotation(rotation_from_quaternion(q_wxyz))


def euler_rate_matrix(psi_rad: ArrayLike) -> FloatArray:
    """The paper's H (..., 3, 3): angular velocity in {O} ``omega = H @ psi_dot``.

    ``H = [[cb cg, -sg, 0], [cb sg, cg, 0], [-sb, 0, 1]]`` for ``psi = (roll, pitch, yaw)``, with
    ``b`` the pitch and ``g`` the yaw.
    """
    psi = check_trailing(psi_rad, "psi_rad", (3,))
    cb, cg = np.cos(psi[..., 1]), np.cos(psi[..., 2])
    sb, sg = np.sin(psi[..., 1]), np.sin(psi[..., 2])
    H = np.zeros(psi.shape[:-1] + (3, 3))
    H[..., 0, 0] = cb * cg
    H[..., 0, 1] = -sg
    H[..., 1, 0] = cb * sg
    H[..., 1, 1] = cg
    H[..., 2, 0] = -sb
    H[..., 2, 2] = 1.0
    return H


def angular_rates(
    psi_rad: ArrayLike, psi_dot: ArrayLike, psi_ddot: ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """Angular velocity and acceleration in {O}, ``(omega, omega_dot)`` each (..., 3), from Z-Y-X
    Euler angles (..., 3) and their first and second time derivatives (rad/s, rad/s^2).

    ``omega = H psi_dot`` and ``omega_dot = H psi_ddot + H_dot psi_dot``, with ``H_dot`` by the
    chain rule on ``H(pitch, yaw)`` (:func:`euler_rate_matrix`).
    """
    psi = check_trailing(psi_rad, "psi_rad", (3,))
    psid = check_trailing(psi_dot, "psi_dot", (3,))
    psidd = check_trailing(psi_ddot, "psi_ddot", (3,))
    H = euler_rate_matrix(psi)
    b, g = psi[..., 1], psi[..., 2]
    bd, gd = psid[..., 1], psid[..., 2]
    sb, cb, sg, cg = np.sin(b), np.cos(b), np.sin(g), np.cos(g)
    Hd = np.zeros(np.broadcast_shapes(psi.shape, psid.shape)[:-1] + (3, 3))
    Hd[..., 0, 0] = -sb * bd * cg - cb * sg * gd
    Hd[..., 0, 1] = -cg * gd
    Hd[..., 1, 0] = -sb * bd * sg + cb * cg * gd
    Hd[..., 1, 1] = -sg * gd
    Hd[..., 2, 0] = -cb * bd
    omega = np.einsum("...ij,...j->...i", H, psid)
    omega_dot = np.einsum("...ij,...j->...i", H, psidd) + np.einsum("...ij,...j->...i", Hd, psid)
    return omega, omega_dot


def _pose_jacobian(psi_rad: ArrayLike, rotation: FloatArray) -> FloatArray:
    psi = check_trailing(psi_rad, "psi_rad", (3,))
    J = np.zeros(psi.shape[:-1] + (6, 6))
    J[..., :3, :3] = np.eye(3)
    J[..., 3:, 3:] = rotation
    return J


def pose_cov_from_euler(psi_rad: ArrayLike, cov_euler: ArrayLike) -> FloatArray:
    """A pose covariance (..., 6, 6) over ``[position, roll, pitch, yaw]`` turned into the camera's
    (``/pose``'s) parametrisation ``[position, rotation vector in {O}]`` (``R' = exp([dtheta]x) R``,
    :mod:`cdpr.calibration.pose`), to first order: ``dtheta = H(psi) dpsi``
    (:func:`euler_rate_matrix`), ``C' = J C J^T`` with ``J = diag(I, H)``."""
    C = check_trailing(cov_euler, "cov_euler", (6, 6))
    J = _pose_jacobian(psi_rad, euler_rate_matrix(psi_rad))
    return np.asarray(J @ C @ np.swapaxes(J, -1, -2), dtype=np.float64)


def pose_cov_to_euler(psi_rad: ArrayLike, cov_rotvec: ArrayLike) -> FloatArray:
    """The inverse of :func:`pose_cov_from_euler`: ``dpsi = H(psi)^-1 dtheta`` (NaN where ``H`` is
    singular, pitch at +-90 deg, and where the covariance is: a frame without one)."""
    C = check_trailing(cov_rotvec, "cov_rotvec", (6, 6), allow_nan=True)
    H = euler_rate_matrix(psi_rad)
    ok = np.abs(np.linalg.det(H)) > 1e-12
    Hinv = np.where(ok[..., None, None], np.linalg.inv(np.where(ok[..., None, None], H, np.eye(3))),
                    np.nan)  # fmt: skip
    J = _pose_jacobian(psi_rad, Hinv)
    return np.asarray(J @ C @ np.swapaxes(J, -1, -2), dtype=np.float64)


def skew(v: ArrayLike) -> FloatArray:
    """Cross-product matrices (..., 3, 3) with ``skew(a) @ b == cross(a, b)`` for ``v`` (..., 3)."""
    a = check_trailing(v, "v", (3,))
    S = np.zeros(a.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -a[..., 2], a[..., 1]
    S[..., 1, 0], S[..., 1, 2] = a[..., 2], -a[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -a[..., 1], a[..., 0]
    return S
