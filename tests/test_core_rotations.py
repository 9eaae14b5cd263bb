"""Rotations against hand-derived cases and scipy's independent implementation."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cdpr.analysis.errors import InputError
from cdpr.analysis.rotations import (
    euler_from_quaternion,
    euler_from_rotation,
    euler_rate_matrix,
    quaternion_from_euler,
    rotation_from_euler,
    rotation_from_quaternion,
    skew,
)

RNG = np.random.default_rng(1)


def test_elementary_rotations_by_hand() -> None:
    # yaw 90 deg: x_P points along y_O
    R = rotation_from_euler([0.0, 0.0, np.pi / 2])
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    # pitch 90 deg about y: x_P points along -z_O
    R = rotation_from_euler([0.0, np.pi / 2, 0.0])
    np.testing.assert_allclose(R @ [1, 0, 0], [0, 0, -1], atol=1e-15)
    # roll 90 deg about x: y_P points along z_O
    R = rotation_from_euler([np.pi / 2, 0.0, 0.0])
    np.testing.assert_allclose(R @ [0, 1, 0], [0, 0, 1], atol=1e-15)


def test_matches_scipy_intrinsic_zyx() -> None:
    psi = RNG.uniform([-np.pi, -1.5, -np.pi], [np.pi, 1.5, np.pi], size=(500, 3))
    ours = rotation_from_euler(psi)
    # R = Rz(gamma) Ry(beta) Rx(alpha) is scipy's intrinsic "ZYX" with angles (gamma, beta, alpha)
    ref = Rotation.from_euler("ZYX", psi[:, ::-1]).as_matrix()
    np.testing.assert_allclose(ours, ref, atol=1e-13)
    q_ref = Rotation.from_euler("ZYX", psi[:, ::-1]).as_quat()  # x, y, z, w
    q_ref = np.concatenate([q_ref[:, 3:], q_ref[:, :3]], axis=1)
    q_ref *= np.sign(q_ref[:, :1])
    np.testing.assert_allclose(quaternion_from_euler(psi), q_ref, atol=1e-12)


def test_round_trips_batched() -> None:
    psi = RNG.uniform([-3, -1.5, -3], [3, 1.5, 3], size=(4, 5, 3))
    np.testing.assert_allclose(euler_from_rotation(rotation_from_euler(psi)), psi, atol=1e-12)
    np.testing.assert_allclose(euler_from_quaternion(quaternion_from_euler(psi)), psi, atol=1e-12)
    R = rotation_from_euler(psi)
    np.testing.assert_allclose(rotation_from_quaternion(quaternion_from_euler(psi)), R, atol=1e-12)


def test_quaternion_of_large_rotations_is_stable() -> None:
    # 180-degree rotations exercise every branch of Shepperd's method
    for axis in np.eye(3):
        R = Rotation.from_rotvec(np.pi * axis).as_matrix()
        q = quaternion_from_euler(euler_from_rotation(R))
        np.testing.assert_allclose(rotation_from_quaternion(q), R, atol=1e-12)


def test_H_maps_euler_rates_to_angular_velocity() -> None:
    """omega from H psi_dot equals vee(R_dot R^T) by central differences (independent)."""
    psi = np.array([0.3, -0.4, 1.1])
    psid = np.array([0.7, -0.2, 0.5])
    h = 1e-6
    Rd = (rotation_from_euler(psi + h * psid) - rotation_from_euler(psi - h * psid)) / (2 * h)
    W = Rd @ rotation_from_euler(psi).T
    omega_fd = np.array([W[2, 1], W[0, 2], W[1, 0]])
    np.testing.assert_allclose(euler_rate_matrix(psi) @ psid, omega_fd, atol=1e-8)


def test_skew_is_cross_product() -> None:
    a, b = RNG.normal(size=(2, 7, 3))
    np.testing.assert_allclose(
        np.einsum("...ij,...j->...i", skew(a), b), np.cross(a, b), atol=1e-14
    )


@pytest.mark.parametrize("bad", [np.zeros(2), np.zeros((3, 2)), np.array([0.0, np.nan, 0.0])])
def test_bad_input_names_expected_and_actual(bad: np.ndarray) -> None:
    with pytest.raises(InputError, match="psi_rad"):
        rotation_from_euler(bad)
