"""Aerodynamic axes, angles, moment transfer and coefficients against hand-derived cases."""

from __future__ import annotations

import numpy as np
import pytest

from cdpr.analysis.aero import (
    COEFFICIENT_NAMES,
    aero_coefficients,
    body_axes_in_platform,
    body_from_tunnel,
    coefficient_matrix,
    dynamic_pressure,
    flow_angles,
    transfer_moment,
    wind_from_body,
)
from cdpr.analysis.errors import InputError
from cdpr.analysis.flow import air_density
from cdpr.analysis.rotations import rotation_from_euler

DEG = np.pi / 180


def test_default_mounting_is_a_half_turn_about_y() -> None:
    # nose upstream (-x_P), canopy up (+z_P): x_B = -x_P, z_B = -z_P, y_B = z_B x x_B = +y_P
    np.testing.assert_allclose(body_axes_in_platform(), np.diag([-1.0, 1.0, -1.0]), atol=1e-15)


def test_air_density_isa_sea_level() -> None:
    # ISA sea level: 101325 Pa, 288.15 K -> 1.2250 kg/m^3 (tabulated)
    assert air_density(101325.0, 288.15) == pytest.approx(1.2250, abs=5e-5)
    assert dynamic_pressure(1.225, 40.0) == pytest.approx(0.5 * 1.225 * 1600.0)
    with pytest.raises(InputError, match="temperature_K"):
        air_density(101325.0, -3.0)


def test_pure_drag_at_zero_angles() -> None:
    # level platform, free stream +x_O: drag pushes the model downstream, F_O = (D, 0, 0)
    q, S, b, c = 500.0, 0.02, 0.25, 0.08
    D = 3.0
    res = aero_coefficients([D, 0, 0, 0, 0, 0], np.eye(3), q, S, b, c)
    assert res.aoa_rad == pytest.approx(0.0, abs=1e-15)
    assert res.sideslip_rad == pytest.approx(0.0, abs=1e-15)
    assert res.drag_N == pytest.approx(D)
    assert res.CD == pytest.approx(D / (q * S))
    for k in ("CY", "CL", "Cl", "Cm", "Cn"):
        assert getattr(res, k) == pytest.approx(0.0, abs=1e-15)
    # body axes: x_B points upstream, so the force is -D along x_B
    np.testing.assert_allclose(res.force_B_N, [-D, 0, 0], atol=1e-15)


def test_pure_lift_and_side_force_at_zero_angles() -> None:
    q, S = 400.0, 0.05
    # up along z_O is lift; +y_O (left looking downstream) is the model's right wing (nose upstream)
    res = aero_coefficients([0, 2.0, 5.0, 0, 0, 0], np.eye(3), q, S, 0.3, 0.1)
    assert res.lift_N == pytest.approx(5.0)
    assert res.CL == pytest.approx(5.0 / (q * S))
    assert res.side_N == pytest.approx(2.0)
    assert res.CY == pytest.approx(2.0 / (q * S))
    assert res.drag_N == pytest.approx(0.0, abs=1e-15)


def test_pitch_and_yaw_give_alpha_and_beta() -> None:
    # nose (-x_P) rotated by +pitch theta about y: nose = (-cos, 0, sin), i.e. up -> alpha = +theta
    a, b = flow_angles(rotation_from_euler([0, 7 * DEG, 0]))
    assert a == pytest.approx(7 * DEG)
    assert b == pytest.approx(0.0, abs=1e-15)
    # yaw +gamma about z: nose turns towards -y_O, the model's left; wind from the right: beta > 0
    a, b = flow_angles(rotation_from_euler([0, 0, 5 * DEG]))
    assert a == pytest.approx(0.0, abs=1e-15)
    assert b == pytest.approx(5 * DEG)
    # roll alone leaves both zero
    a, b = flow_angles(rotation_from_euler([20 * DEG, 0, 0]))
    assert abs(a) < 1e-15 and abs(b) < 1e-15


def test_ninety_degree_yaw() -> None:
    # yaw 90 deg: nose along -y_O; relative wind (model velocity -x_O) is along +y_B: beta = 90 deg.
    R = rotation_from_euler([0, 0, np.pi / 2])
    np.testing.assert_allclose(body_from_tunnel(R) @ [-1.0, 0, 0], [0, 1, 0], atol=1e-15)
    res = aero_coefficients([4.0, 0, 0, 0, 0, 0], R, 100.0, 0.1, 1.0, 0.1)
    assert res.sideslip_rad == pytest.approx(np.pi / 2)
    assert res.aoa_rad == pytest.approx(0.0, abs=1e-12)
    # a force along the free stream is still pure drag in wind axes
    assert res.drag_N == pytest.approx(4.0)
    assert res.side_N == pytest.approx(0.0, abs=1e-12)
    assert res.lift_N == pytest.approx(0.0, abs=1e-12)
    # ... but in body axes it is along -y_B (pushing the model's right side)
    np.testing.assert_allclose(res.force_B_N, [0, -4.0, 0], atol=1e-12)


def test_lift_and_drag_rotate_with_alpha() -> None:
    # at alpha = 10 deg the lift is perpendicular to the free stream: a force straight up in {O}
    # is pure lift, a force along +x_O pure drag, whatever the pitch.
    R = rotation_from_euler([0, 10 * DEG, 0])
    res = aero_coefficients([1.0, 0, 2.0, 0, 0, 0], R, 100.0, 0.1, 1.0, 0.1)
    assert res.drag_N == pytest.approx(1.0)
    assert res.lift_N == pytest.approx(2.0)
    # in body axes (x_B = nose, tilted up): F_B,x = -1 cos10 + 2 sin10, F_B,z = -(1 sin10 + 2 cos10)
    s, c = np.sin(10 * DEG), np.cos(10 * DEG)
    np.testing.assert_allclose(res.force_B_N, [-c + 2 * s, 0, -(s + 2 * c)], atol=1e-12)


def test_wind_axes_rotation_is_orthonormal_and_x_is_the_velocity() -> None:
    a, b = 0.3, -0.2
    R = wind_from_body(a, b)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-15)
    assert np.linalg.det(R) == pytest.approx(1.0)
    v_B = np.array([np.cos(a) * np.cos(b), np.sin(b), np.sin(a) * np.cos(b)])
    np.testing.assert_allclose(R @ v_B, [1, 0, 0], atol=1e-15)


def test_moment_transfer_of_a_pure_force() -> None:
    # a force F through the point r: about P the moment is r x F; about r it vanishes
    F = np.array([1.0, -2.0, 0.5])
    r = np.array([0.1, 0.05, -0.02])
    M_P = np.array(
        [0.05 * 0.5 - (-0.02) * (-2.0), -0.02 * 1.0 - 0.1 * 0.5, 0.1 * -2.0 - 0.05 * 1.0]
    )
    w = np.concatenate([F, M_P])
    np.testing.assert_allclose(transfer_moment(w, r), np.concatenate([F, np.zeros(3)]), atol=1e-15)
    # and a pure drag through an MRP 0.1 m ahead of P (upstream, x_P = -0.1) has no pitching moment
    res = aero_coefficients(
        [3.0, 0, 0, 0, 0, 0], np.eye(3), 100.0, 0.1, 1.0, 0.1, mrp_P_m=[-0.1, 0, 0]
    )
    assert res.Cm == pytest.approx(0.0, abs=1e-15)


def test_moment_coefficients_by_hand() -> None:
    # lift L = 2 N acting 0.05 m downstream of the MRP (at P; MRP at x_P = -0.05): the lift behind
    # the MRP pitches the nose down, a negative pitching moment.  About P the moment is zero
    # (force through P); about the MRP it is -r x F with r = (-0.05, 0, 0) -> M = (0, -0.1, 0) in {O}.
    # In body axes (y_B = y_O) m = -0.1 N m: nose-down, as expected.
    q, S, b, c = 200.0, 0.04, 0.5, 0.1
    res = aero_coefficients([0, 0, 2.0, 0, 0, 0], np.eye(3), q, S, b, c, mrp_P_m=[-0.05, 0, 0])
    assert res.moment_B_Nm[1] == pytest.approx(-0.1)
    assert res.Cm == pytest.approx(-0.1 / (q * S * c))
    # a moment about +x_O (downstream) is a negative rolling moment (x_B points upstream)
    res = aero_coefficients([0, 0, 0, 0.3, 0, 0.2], np.eye(3), q, S, b, c)
    assert res.Cl == pytest.approx(-0.3 / (q * S * b))
    # +z_O moment: z_B = -z_O, so yawing moment n = -0.2
    assert res.Cn == pytest.approx(-0.2 / (q * S * b))


def test_batched_and_custom_nose() -> None:
    # nose along +x_P (downstream-facing model) at zero pose: drag along +x_O is then along +x_B
    res = aero_coefficients(
        np.tile([1.0, 0, 0, 0, 0, 0], (3, 2, 1)), np.eye(3), 10.0, 1.0, 1.0, 1.0, nose_P=[1, 0, 0]
    )
    assert res.CD.shape == (3, 2)
    # the model faces downstream: it "flies" backwards, alpha = 180 deg
    np.testing.assert_allclose(np.abs(res.aoa_rad), np.pi)
    np.testing.assert_allclose(res.drag_N, 1.0)
    with pytest.raises(InputError, match="up_P"):
        body_axes_in_platform([1, 0, 0], [2, 0, 0])


def test_coefficient_matrix_by_hand_and_against_aero_coefficients() -> None:
    # level platform, MRP at P: D = Fx, Y = Fy, L = Fz, l = -Mx, m = My, n = -Mz (x_B = -x_O, z_B = -z_O)
    q, S, b, c = 250.0, 0.02, 0.25, 0.08
    K = coefficient_matrix(np.eye(3), q, S, b, c)
    np.testing.assert_allclose(
        K, np.diag([1, 1, 1, -1 / b, 1 / c, -1 / b]) / (q * S), rtol=1e-14, atol=1e-14
    )
    # at any attitude and MRP, K @ W reproduces aero_coefficients (hand-checked above)
    rng = np.random.default_rng(0)
    R = rotation_from_euler(rng.normal(0, 0.3, (5, 3)))
    W = rng.normal(size=(5, 6))
    K = coefficient_matrix(R, q, S, b, c, [0.02, 0.01, -0.03])
    res = aero_coefficients(W, R, q, S, b, c, [0.02, 0.01, -0.03])
    coeffs = np.stack([getattr(res, n) for n in COEFFICIENT_NAMES], axis=-1)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", K, W), coeffs, rtol=1e-12, atol=1e-14)
