"""Wrench recovery (tare, absolute, dynamic correction) against hand derivations and an independent
per-cable force/moment sum (scipy rotations, numpy least squares)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cdpr.analysis.errors import InputError
from cdpr.analysis.kinematics import structure_matrix
from cdpr.analysis.rig import Rig
from cdpr.analysis.rigs import flat_rig
from cdpr.analysis.wrench import (
    inertia_wrench_from_poses,
    recover_wrench,
    wrench_absolute,
    wrench_tare,
)

G0 = 9.80665


def _rig(anchors, attach, mass=1.0, com=(0, 0, 0), gravity=(0, 0, -G0), inertia=None) -> Rig:
    m = len(anchors)
    return Rig(
        name="hand",
        cable_names=tuple(f"c{i}" for i in range(m)),
        anchors_O_m=np.array(anchors, dtype=float),
        attach_P_m=np.array(attach, dtype=float),
        mass_kg=mass,
        com_P_m=np.array(com, dtype=float),
        inertia_P_kgm2=np.zeros((3, 3)) if inertia is None else np.array(inertia),
        t_min_N=np.zeros(m),
        t_max_N=np.full(m, 1000.0),
        gravity_O_mps2=np.array(gravity, dtype=float),
    )


def test_tare_two_opposed_cables_by_hand() -> None:
    # cables from P to (-1,0,0) and (+1,0,0); wind-on the +x cable pulls 2 N harder, so the cables
    # push the platform by +2 N along x and the external load must be -2 N along x.
    A = structure_matrix([[-1.0, 0, 0], [1.0, 0, 0]], np.zeros((2, 3)), np.zeros(3), np.eye(3))
    W = wrench_tare(A, [10.0, 12.0], [10.0, 10.0])
    np.testing.assert_allclose(W, [-2.0, 0, 0, 0, 0, 0], atol=1e-12)


def test_absolute_vertical_cable_with_gravity_by_hand() -> None:
    rig = _rig([[0, 0, 1.0]], [[0, 0, 0]], mass=1.0)
    q = np.zeros(6)
    # tension equal to the weight: no external load
    np.testing.assert_allclose(recover_wrench(rig, q, [G0]), np.zeros(6), atol=1e-12)
    # 12 N: an external force of 12 - 9.80665 N downwards
    np.testing.assert_allclose(
        recover_wrench(rig, q, [12.0]), [0, 0, -(12.0 - G0), 0, 0, 0], atol=1e-12
    )


def test_absolute_moment_by_hand() -> None:
    # cable force (0, 0, 5) N at r = (0.1, 0, 0): moment r x F = (0, -0.5, 0); no gravity
    rig = _rig([[0.1, 0, 1.0]], [[0.1, 0, 0]], gravity=(0, 0, 0))
    np.testing.assert_allclose(
        recover_wrench(rig, np.zeros(6), [5.0]), [0, 0, -5.0, 0, 0.5, 0], atol=1e-12
    )


def test_gravity_moment_of_offset_com_by_hand() -> None:
    # com 0.2 m along x_P, platform yawed 90 deg: R c = (0, 0.2, 0), weight (0, 0, -2 g):
    # G = [0, 0, -2g, (0.2)(-2g), 0, 0].  One vertical cable through P carries 2g; the absolute method
    # must report the gravity moment as external moment -(G_M) since nothing else balances it.
    rig = _rig([[0, 0, 1.0]], [[0, 0, 0]], mass=2.0, com=(0.2, 0, 0))
    q = np.array([0, 0, 0, 0, 0, np.pi / 2])
    W = recover_wrench(rig, q, [2 * G0])
    np.testing.assert_allclose(W, [0, 0, 0, 0.4 * G0, 0, 0], atol=1e-12)


def _independent_cable_wrench(rig: Rig, q: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Sum of the cable forces and their moments about P, one cable at a time (scipy rotation)."""
    R = Rotation.from_euler("ZYX", [q[5], q[4], q[3]]).as_matrix()
    F = np.zeros(3)
    M = np.zeros(3)
    for b, pp, t in zip(rig.anchors_O_m, rig.attach_P_m, T, strict=True):
        r = R @ pp
        d = b - (q[:3] + r)
        f = t * d / np.sqrt(d @ d)
        F += f
        M += np.cross(r, f)
    return np.concatenate([F, M])


def test_absolute_and_tare_recover_a_known_load_on_the_flat_rig() -> None:
    """Tensions balancing gravity + a chosen wrench (solved by scipy on an independent A) give it back."""
    rig = flat_rig(51, 28, 0.67, 0.5)
    rng = np.random.default_rng(3)
    m_g = rig.mass_kg * G0
    for _ in range(5):
        q = np.concatenate(
            [rig.reference_position_O_m + rng.normal(0, 0.01, 3), rng.normal(0, 0.05, 3)]
        )
        # independent structure matrix: columns = wrench of a unit tension in each cable
        A = np.stack([_independent_cable_wrench(rig, q, e) for e in np.eye(8)], axis=1)
        W_true = rng.normal(0, [3, 1, 5, 0.1, 0.3, 0.1])
        G = np.array([0, 0, -m_g, 0, 0, 0])  # com at P
        # A T = -(G + W): least-squares particular solution moved near 100 N along the null space
        base = np.linalg.lstsq(A, -(G + W_true), rcond=None)[0]
        N = np.linalg.svd(A)[2][6:].T  # null space (8, 2)
        T = base + N @ np.linalg.lstsq(N, 100.0 - base, rcond=None)[0]
        assert np.allclose(A @ T, -(G + W_true), atol=1e-9)
        np.testing.assert_allclose(recover_wrench(rig, q, T), W_true, atol=1e-9)
        base0 = np.linalg.lstsq(A, -G, rcond=None)[0]
        T0 = base0 + N @ np.linalg.lstsq(N, 100.0 - base0, rcond=None)[0]
        assert np.allclose(A @ T0, -G, atol=1e-9)
        np.testing.assert_allclose(recover_wrench(rig, q, T, tare_tensions_N=T0), W_true, atol=1e-9)


def test_batched_shapes_and_broadcast() -> None:
    rig = flat_rig(51, 28, 0.67, 0.5)
    q = np.tile(np.concatenate([rig.reference_position_O_m, np.zeros(3)]), (4, 3, 1))
    T = np.full((4, 3, 8), 100.0)
    W = recover_wrench(rig, q, T)
    assert W.shape == (4, 3, 6)
    # every entry is the same pose and tensions: W_ext = -(cable wrench) - G, G = (0, 0, -m g, 0...)
    G = np.array([0, 0, -rig.mass_kg * G0, 0, 0, 0])
    expect = -_independent_cable_wrench(rig, q[0, 0], T[0, 0]) - G
    np.testing.assert_allclose(W, np.broadcast_to(expect, (4, 3, 6)), atol=1e-9)
    assert recover_wrench(rig, q, T, tare_tensions_N=T).shape == (4, 3, 6)
    np.testing.assert_allclose(recover_wrench(rig, q, T, tare_tensions_N=T), 0.0, atol=1e-12)


def test_dynamic_correction_constant_acceleration_by_hand() -> None:
    # x = a t^2 / 2: M qdd + C = (m a, 0, 0, 0, 0, 0); central differences are exact on quadratics.
    a, m = 0.8, 2.0
    t_ns = np.arange(0, 50) * 10_000_000  # 100 Hz
    t = t_ns * 1e-9
    poses = np.zeros((50, 6))
    poses[:, 0] = 0.5 + 0.5 * a * t**2
    poses[:, 2] = 1.0
    D = inertia_wrench_from_poses(m, np.zeros(3), np.eye(3) * 0.1, poses, t_ns)
    np.testing.assert_allclose(D, np.tile([m * a, 0, 0, 0, 0, 0], (50, 1)), atol=1e-6)
    # a single vertical cable carrying the weight: nothing but the external load pushes the
    # platform along x, so by Newton W_ext = m a x: W_ext = -A T - G + D = (m a, 0, ...)
    rig = _rig([[0.5, 0, 3.0]], [[0, 0, 0]], mass=m)
    A = structure_matrix(rig.anchors_O_m, rig.attach_P_m, [0.5, 0, 1.0], np.eye(3))
    W = wrench_absolute(A, [m * G0], [0, 0, -m * G0, 0, 0, 0], D[0])
    np.testing.assert_allclose(W, [m * a, 0, 0, 0, 0, 0], atol=1e-6)


def test_dynamic_correction_centripetal_by_hand() -> None:
    # constant yaw rate w, com at distance r along x_P: F = -m w^2 R c (centripetal), M = R c x F = 0
    # (plus I w_dot + w x I w = 0 for a diagonal I and rotation about z).
    m, r, w = 1.5, 0.1, 2.0
    t_ns = np.arange(0, 2001) * 1_000_000  # 1 kHz, 2 s
    gamma = w * t_ns * 1e-9
    poses = np.zeros((t_ns.size, 6))
    poses[:, 5] = np.angle(np.exp(1j * gamma))  # wrapped to (-pi, pi]: must be unwrapped inside
    D = inertia_wrench_from_poses(m, [r, 0, 0], np.diag([0.1, 0.2, 0.3]), poses, t_ns)
    rc = np.stack([r * np.cos(gamma), r * np.sin(gamma), 0 * gamma], axis=-1)
    expect = np.concatenate([-m * w**2 * rc, np.zeros_like(rc)], axis=-1)
    np.testing.assert_allclose(D[2:-2], expect[2:-2], atol=1e-5)


def test_bad_shapes_raise() -> None:
    A = np.zeros((6, 8))
    with pytest.raises(InputError, match="tensions_wind_on_N"):
        wrench_tare(A, np.zeros(7), np.zeros(8))
    with pytest.raises(InputError, match="A: expected"):
        wrench_absolute(np.zeros((5, 8)), np.zeros(8), np.zeros(6))
    with pytest.raises(InputError, match="finite"):
        wrench_tare(A, np.full(8, np.nan), np.zeros(8))
