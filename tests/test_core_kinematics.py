"""Structure matrix, gravity and inertia wrenches against hand derivations and first principles."""

from __future__ import annotations

import numpy as np
import pytest

from cdpr.analysis.dynamics import finite_difference, gravity_wrench, inertia_wrench
from cdpr.analysis.errors import InputError
from cdpr.analysis.kinematics import cable_geometry, structure_matrix, structure_matrix_at
from cdpr.analysis.rigs import cubic_rig, flat_rig
from cdpr.analysis.rotations import rotation_from_euler

RNG = np.random.default_rng(7)


def test_structure_matrix_by_hand() -> None:
    # one cable straight up from a platform point 0.1 m along x_P; platform yawed by 90 degrees
    anchors = np.array([[0.0, 0.1, 2.0]])
    attach = np.array([[0.1, 0.0, 0.0]])
    R = rotation_from_euler([0.0, 0.0, np.pi / 2])  # x_P -> y_O, so r = (0, 0.1, 0)
    geo = cable_geometry(anchors, attach, np.array([0.0, 0.0, 1.0]), R)
    np.testing.assert_allclose(geo.r_O_m[0], [0, 0.1, 0], atol=1e-15)
    np.testing.assert_allclose(geo.length_m, [1.0], atol=1e-15)
    np.testing.assert_allclose(geo.u_O[0], [0, 0, 1], atol=1e-15)
    # r x u = (0, 0.1, 0) x (0, 0, 1) = (0.1, 0, 0)
    np.testing.assert_allclose(geo.A[:, 0], [0, 0, 1, 0.1, 0, 0], atol=1e-15)


def test_static_equilibrium_of_a_hanging_box() -> None:
    """Four vertical cables at the corners of a square carry a quarter of the weight each."""
    a = 0.2
    corners = np.array([[a, a, 0], [a, -a, 0], [-a, a, 0], [-a, -a, 0]], dtype=float)
    anchors = corners + [0, 0, 3.0]
    A = structure_matrix(anchors, corners, np.zeros(3), np.eye(3))
    G = gravity_wrench(2.0, np.zeros(3), np.eye(3), [0, 0, -10.0])
    np.testing.assert_allclose(G, [0, 0, -20, 0, 0, 0])
    T = np.full(4, 5.0)  # 20 N / 4 cables
    np.testing.assert_allclose(A @ T, -G, atol=1e-12)


def test_gravity_moment_of_offset_centre_of_mass_by_hand() -> None:
    # c = 0.1 m along x_P, yaw 90 deg: R c = (0, 0.1, 0); m g = (0, 0, -9.81*2)
    G = gravity_wrench(2.0, [0.1, 0, 0], rotation_from_euler([0, 0, np.pi / 2]), [0, 0, -9.81])
    # (0, 0.1, 0) x (0, 0, -19.62) = (0.1 * -19.62 - 0, 0, 0)
    np.testing.assert_allclose(G, [0, 0, -19.62, -1.962, 0, 0], atol=1e-12)


def test_batched_equals_single_and_pose_form() -> None:
    rig = flat_rig(51, 28, 0.67, 0.5)
    poses = rig.reference_position_O_m + RNG.normal(scale=[0.01, 0.01, 0.01], size=(3, 4, 3))
    psi = RNG.normal(scale=0.05, size=(3, 4, 3))
    A = structure_matrix(rig.anchors_O_m, rig.attach_P_m, poses, rotation_from_euler(psi))
    assert A.shape == (3, 4, 6, 8)
    i, j = 2, 1
    single = structure_matrix(
        rig.anchors_O_m, rig.attach_P_m, poses[i, j], rotation_from_euler(psi[i, j])
    )
    np.testing.assert_allclose(A[i, j], single, atol=1e-15)
    q = np.concatenate([poses, psi], axis=-1)
    np.testing.assert_allclose(structure_matrix_at(rig.anchors_O_m, rig.attach_P_m, q), A, atol=0)


def test_structure_matrix_is_the_jacobian_of_cable_lengths() -> None:
    """Paper eq. (3): dL/dt = -A^T [p_dot; omega]; check by central differences of the lengths."""
    rig = cubic_rig(0.15, 0.075, 0.075)
    p = rig.reference_position_O_m + [0.02, -0.01, 0.03]
    psi = np.array([0.05, -0.03, 0.1])
    v, omega = np.array([0.1, -0.2, 0.3]), np.array([0.2, 0.1, -0.3])
    h = 1e-6

    def lengths(p_, R_):
        return cable_geometry(rig.anchors_O_m, rig.attach_P_m, p_, R_).length_m

    R = rotation_from_euler(psi)
    from scipy.spatial.transform import Rotation

    dR = Rotation.from_rotvec(omega * h).as_matrix()
    Ld = (lengths(p + v * h, dR @ R) - lengths(p - v * h, dR.T @ R)) / (2 * h)
    A = structure_matrix(rig.anchors_O_m, rig.attach_P_m, p, R)
    np.testing.assert_allclose(Ld, -A.T @ np.concatenate([v, omega]), atol=1e-7)


def test_inertia_wrench_against_newton_euler_by_differences() -> None:
    """M qdd + C against momentum derivatives computed from positions alone (independent path)."""
    m = 1.7
    c = np.array([0.03, -0.02, 0.01])
    I_P = np.array([[0.05, 0.001, 0.0], [0.001, 0.04, 0.002], [0.0, 0.002, 0.03]])
    I_c = I_P - m * (c @ c * np.eye(3) - np.outer(c, c))  # parallel-axis theorem

    def q(t):
        return np.array(
            [
                0.1 * np.sin(2 * t),
                0.05 * np.cos(3 * t),
                0.5 + 0.02 * t**2,
                0.3 * np.sin(t),
                0.2 * np.sin(1.5 * t),
                0.4 * np.cos(0.7 * t),
            ]
        )

    t0, h = 0.37, 1e-4

    def com(t):
        return q(t)[:3] + rotation_from_euler(q(t)[3:]) @ c

    def omega(t):
        Rd = (rotation_from_euler(q(t + h)[3:]) - rotation_from_euler(q(t - h)[3:])) / (2 * h)
        W = Rd @ rotation_from_euler(q(t)[3:]).T
        return np.array([W[2, 1], W[0, 2], W[1, 0]])

    def h_c(t):  # angular momentum about the centre of mass, {O}
        R = rotation_from_euler(q(t)[3:])
        return R @ I_c @ R.T @ omega(t)

    F = m * (com(t0 + h) - 2 * com(t0) + com(t0 - h)) / h**2
    M = (h_c(t0 + h) - h_c(t0 - h)) / (2 * h) + np.cross(com(t0) - q(t0)[:3], F)
    qd = (q(t0 + h) - q(t0 - h)) / (2 * h)
    qdd = (q(t0 + h) - 2 * q(t0) + q(t0 - h)) / h**2
    ours = inertia_wrench(m, c, I_P, q(t0), qd, qdd)
    np.testing.assert_allclose(ours, np.concatenate([F, M]), rtol=1e-4, atol=1e-6)


def test_finite_difference_of_a_quadratic_is_exact() -> None:
    t_ns = np.array([0, 1_000_000, 2_500_000, 4_000_000, 5_000_000])
    t = t_ns * 1e-9
    v = np.stack([3 * t**2 + 2 * t, -t], axis=1)
    np.testing.assert_allclose(
        finite_difference(v, t_ns), np.stack([6 * t + 2, -np.ones_like(t)], 1), atol=1e-9
    )
    with pytest.raises(InputError, match="increasing"):
        finite_difference(v, t_ns[::-1])


def test_zero_length_cable_is_refused() -> None:
    with pytest.raises(InputError, match="zero length"):
        cable_geometry(np.zeros((1, 3)), np.zeros((1, 3)), np.zeros(3), np.eye(3))
