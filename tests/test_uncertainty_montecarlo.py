"""The linearised wrench covariance against a Monte Carlo run and hand-derived cases.

Monte Carlo: the true pose and tensions are fixed; each sample measures the pose with Gaussian noise
(0.5 mm, 0.1 deg: the paper's camera precision) and the tensions with 0.05 N load-cell noise, and
recomputes the wrench with the wrench-recovery functions.  With N samples the sample covariance S of
Gaussian data, whitened by the predicted covariance (P^-1/2 S P^-T/2), has diagonal entries with
standard error sqrt(2/N) and off-diagonal ones 1/sqrt(N) around the identity when the prediction is
right; we allow 5 standard errors (false-alarm rate below 1e-4 per entry, and the seed is fixed).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cdpr.analysis.dynamics import gravity_wrench
from cdpr.analysis.errors import InputError
from cdpr.analysis.kinematics import structure_matrix
from cdpr.analysis.rotations import rotation_from_euler
from cdpr.analysis.uncertainty import (
    pose_jacobian,
    tension_noise_covariance,
    wrench_covariance,
)
from cdpr.analysis.wrench import recover_wrench
from cdpr.pipelines.config import load_rig

FLAT = Path(__file__).resolve().parents[1] / "data_samples" / "flat_optimum.toml"

N = 40_000
SIGMA_T = 0.05  # N
SIGMA_POS = 0.5e-3  # m
SIGMA_ANG = np.deg2rad(0.1)  # rad
POSE_SD = np.array([SIGMA_POS] * 3 + [SIGMA_ANG] * 3)


def _setup():
    rig = load_rig(FLAT)
    q = np.concatenate([rig.reference_position_O_m + [0.01, -0.005, 0.02], [0.01, 0.02, -0.01]])
    R = rotation_from_euler(q[3:])
    A = structure_matrix(rig.anchors_O_m, rig.attach_P_m, q[:3], R)
    G = gravity_wrench(rig.mass_kg, rig.com_P_m, R, rig.gravity_O_mps2)
    W_aero = np.array([3.0, 0.3, 4.0, 0.005, 0.02, -0.005])
    # tensions balancing the load, min |T - 160 N| (closed form by numpy's pseudo-inverse)
    t_mid = np.full(8, 160.0)
    Tw = t_mid + np.linalg.pinv(A) @ (-(G + W_aero) - A @ t_mid)
    T0 = t_mid + np.linalg.pinv(A) @ (-G - A @ t_mid)
    assert np.all(Tw > 35) and np.all(T0 > 35)
    return rig, q, Tw, T0


def _whitened_deviation(samples: np.ndarray, predicted: np.ndarray) -> np.ndarray:
    S = np.cov(samples, rowvar=False)
    L = np.linalg.cholesky(predicted)
    Li = np.linalg.inv(L)
    return Li @ S @ Li.T - np.eye(6)


def _check(samples: np.ndarray, predicted: np.ndarray) -> None:
    dev = _whitened_deviation(samples, predicted)
    se = np.full((6, 6), 1 / np.sqrt(N))
    np.fill_diagonal(se, np.sqrt(2 / N))
    assert np.all(np.abs(dev) < 5 * se), f"whitened covariance deviation / SE:\n{dev / se}"


@pytest.mark.parametrize("method", ["absolute", "tare"])
def test_covariance_matches_monte_carlo(method: str) -> None:
    rig, q, Tw, T0 = _setup()
    rng = np.random.default_rng(12345 if method == "absolute" else 54321)
    q_meas = q + rng.normal(size=(N, 6)) * POSE_SD
    Tw_meas = Tw + rng.normal(0, SIGMA_T, size=(N, 8))
    if method == "tare":
        T0_meas = T0 + rng.normal(0, SIGMA_T, size=(N, 8))
        W = recover_wrench(rig, q_meas, Tw_meas, tare_tensions_N=T0_meas)
        cov = wrench_covariance(rig, q, Tw, SIGMA_T, POSE_SD, tare_tensions_N=T0)
    else:
        W = recover_wrench(rig, q_meas, Tw_meas)
        cov = wrench_covariance(rig, q, Tw, SIGMA_T, POSE_SD)
    _check(W, cov.total)
    # and the pose part matters: without it the prediction would fail the same test
    dev = _whitened_deviation(W, cov.from_tensions + 1e-30 * np.eye(6))
    assert np.max(np.abs(dev)) > 5 * np.sqrt(2 / N)


def test_pose_part_alone_matches_monte_carlo() -> None:
    rig, q, Tw, _ = _setup()
    rng = np.random.default_rng(777)
    q_meas = q + rng.normal(size=(N, 6)) * POSE_SD
    W = recover_wrench(rig, q_meas, np.broadcast_to(Tw, (N, 8)))
    cov = wrench_covariance(rig, q, Tw, 0.0, POSE_SD)
    np.testing.assert_allclose(cov.from_tensions, 0.0)
    _check(W, cov.total)


def test_tension_part_by_hand() -> None:
    # two opposed cables along x and one vertical: F = (T2 - T1, 0, T3); sigma 0.1 and 0.2 N
    A = structure_matrix(
        [[-1.0, 0, 0], [1.0, 0, 0], [0, 0, 1.0]], np.zeros((3, 3)), np.zeros(3), np.eye(3)
    )
    C = tension_noise_covariance(A, [0.1, 0.1, 0.2])
    expect = np.zeros((6, 6))
    expect[0, 0] = 0.1**2 + 0.1**2
    expect[2, 2] = 0.2**2
    np.testing.assert_allclose(C, expect, atol=1e-15)


def test_pose_jacobian_by_hand() -> None:
    # one cable from P to an anchor 2 m above carrying T: F = T (b - p)/|b - p|.
    # dF_x/dx = -T/L, dF_z/dz = 0 (direction unchanged along the cable), L = 2
    T, b = 10.0, np.array([0.0, 0.0, 2.0])

    def w(qp: np.ndarray) -> np.ndarray:
        d = b - qp[..., :3]
        f = T * d / np.linalg.norm(d, axis=-1, keepdims=True)
        return np.concatenate([f, np.zeros_like(f)], axis=-1)

    J = pose_jacobian(w, np.zeros(6))
    assert J[0, 0] == pytest.approx(-T / 2, rel=1e-8)
    assert J[1, 1] == pytest.approx(-T / 2, rel=1e-8)
    assert J[2, 2] == pytest.approx(0.0, abs=1e-6)
    with pytest.raises(InputError):
        pose_jacobian(w, np.zeros(6), step=[0, 1, 1, 1, 1, 1])
