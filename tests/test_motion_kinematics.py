"""The commanded oscillation, the cables along it and the pose from cable lengths
(``cdpr.analysis.motion``) against the issue's formula, differences of independently computed
lengths, a Monte Carlo of the forward kinematics, and the tensions that carry a motion against an
independent Newton-Euler and quadprog (tests/_oscillation_truth.py)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from _oscillation_truth import (
    controller,
    gravity,
    lengths,
    momentum_rate,
    motion,
    read_rig,
    structure,
)

from cdpr.analysis.errors import InputError
from cdpr.analysis.motion import (
    Motion,
    Oscillation,
    cable_motion,
    forward_kinematics,
    motion_tensions,
    oscillation_motion,
)
from cdpr.daq.schema import load_rig

ROOT = Path(__file__).resolve().parents[1]
RIG = ROOT / "data_samples" / "flat_optimum.toml"


@pytest.mark.parametrize(("axis", "j", "amp"), [("pitch", 4, 0.0873), ("heave", 2, 0.004)])
def test_motion_is_the_issue_formula_with_its_derivatives(axis: str, j: int, amp: float) -> None:
    f, n_set, n_cyc = 2.0, 2, 3
    osc = Oscillation(axis, amp, f, n_cyc, n_set)
    mean = np.array([0.5, 0.0, 0.335, 0.0, 0.05, 0.01])
    t = np.linspace(-0.2, osc.duration_s + 0.3, 4001)
    mo = oscillation_motion(t, mean, osc)
    np.testing.assert_allclose(mo.pose, motion(t, mean, j, amp, f, n_set, n_cyc), atol=1e-15)
    h = 1e-5  # the rate and acceleration against central differences of the formula
    qp, qm = (motion(t + s, mean, j, amp, f, n_set, n_cyc) for s in (h, -h))
    np.testing.assert_allclose(mo.rate, (qp - qm) / (2 * h), atol=1e-6 * amp * 2 * np.pi * f)
    q0 = motion(t, mean, j, amp, f, n_set, n_cyc)
    acc = (qp - 2 * q0 + qm) / h**2
    np.testing.assert_allclose(mo.accel, acc, atol=2e-3 * amp * (2 * np.pi * f) ** 2)
    # continuous at every join (whole cycles): no jump of pose, rate or acceleration
    assert np.abs(np.diff(mo.accel[:, j])).max() < 0.02 * amp * (2 * np.pi * f) ** 2
    assert osc.window_s == (1.0, 2.5) and osc.duration_s == 3.0


def test_cable_speeds_and_accelerations_are_the_derivatives_of_the_lengths() -> None:
    trig = read_rig(RIG)
    rig = load_rig(RIG)
    rng = np.random.default_rng(4)
    q0 = np.concatenate([trig.home, [0.02, 0.08, -0.03]])
    qd = rng.normal(0, [0.05, 0.05, 0.05, 0.5, 0.5, 0.5])
    qdd = rng.normal(0, [0.5, 0.5, 0.5, 5, 5, 5])

    def q(t: float) -> np.ndarray:  # a pose path with this rate and acceleration at t = 0
        return q0 + qd * t + 0.5 * qdd * t * t

    cm = cable_motion(rig.anchors_O_m, rig.attach_P_m, q0, qd, qdd)
    h = 1e-4
    L = [lengths(trig, q(s)) for s in (-h, 0.0, h)]
    np.testing.assert_allclose(cm.length_m, L[1], atol=1e-12)
    np.testing.assert_allclose(cm.speed_mps, (L[2] - L[0]) / (2 * h), atol=1e-8)
    np.testing.assert_allclose(cm.accel_mps2, (L[2] - 2 * L[1] + L[0]) / h**2, atol=2e-5)


def test_forward_kinematics_recovers_the_pose_with_the_covariance_it_claims() -> None:
    trig = read_rig(RIG)
    rig = load_rig(RIG)
    rng = np.random.default_rng(7)
    q_true = np.concatenate([trig.home + [0.004, -0.003, 0.002], [0.01, 0.06, -0.005]])
    n, sd = 4000, 2e-5
    L = np.tile(lengths(trig, q_true), (n, 1)) + sd * rng.standard_normal((n, 8))
    start = [*rig.reference_position_O_m, 0.0, 0.0, 0.0]
    fk = forward_kinematics(rig.anchors_O_m, rig.attach_P_m, L, sd, start)
    assert fk.converged.all() and fk.iterations < 20
    err = fk.pose - q_true
    # noise-free lengths give the pose to 1e-9; with noise, the spread is the claimed covariance
    exact = forward_kinematics(rig.anchors_O_m, rig.attach_P_m, lengths(trig, q_true)[None], sd,
                               q_true + 0.01)  # fmt: skip
    np.testing.assert_allclose(exact.pose[0], q_true, atol=1e-9)
    emp = np.cov(err.T)
    claim = fk.covariance.mean(axis=0)
    ratio = np.diag(emp) / np.diag(claim)
    assert np.all(np.abs(ratio - 1) < 0.1), ratio  # 4000 draws: +-4.5 % (2 sigma) per variance
    assert abs(np.abs(err.mean(axis=0) / np.sqrt(np.diag(claim))).max()) < 0.1
    assert fk.chi2.mean() == pytest.approx(8 - 6, rel=0.1)


def test_forward_kinematics_refuses_bad_input() -> None:
    rig = load_rig(RIG)
    with pytest.raises(InputError, match="length_sd_m"):
        forward_kinematics(rig.anchors_O_m, rig.attach_P_m, np.ones((2, 8)), 0.0, np.zeros(6))
    with pytest.raises(InputError, match="lengths_m"):
        forward_kinematics(rig.anchors_O_m, rig.attach_P_m, np.ones((2, 7)), 1e-5, np.zeros(6))


def test_tensions_that_carry_a_motion_against_newton_euler_and_quadprog() -> None:
    """A yaw-and-pitch wobble with the centre of mass off P: the tensions satisfy the independent
    Newton-Euler ``A T + G + W = D`` (momentum differences) and are quadprog's min |T - T_mid|."""
    trig = read_rig(RIG)
    rig = load_rig(RIG)
    import dataclasses

    com = np.array([0.004, -0.002, 0.003])
    rig = dataclasses.replace(rig, com_P_m=com)  # the Rig re-validates
    trig = dataclasses.replace(trig, com=com)
    w1, w2 = 2 * math.pi * 1.5, 2 * math.pi * 2.3

    def pose(t: float) -> np.ndarray:
        return np.concatenate([trig.home + [0.002 * math.sin(w2 * t), 0, 0],
                               [0.0, 0.05 * math.sin(w1 * t), 0.004 * math.cos(w2 * t)]])  # fmt: skip

    t = np.linspace(0.0, 1.0, 9)
    h = 1e-5
    q = np.array([pose(s) for s in t])
    qd = np.array([(pose(s + h) - pose(s - h)) / (2 * h) for s in t])
    qdd = np.array([(pose(s + h) - 2 * pose(s) + pose(s - h)) / h**2 for s in t])
    W = np.tile([0.3, -0.1, 1.2, 0.01, -0.02, 0.005], (t.size, 1))
    mt = motion_tensions(rig, Motion(q, qd, qdd), W, "exact")
    assert mt.result.feasible.all()
    for i, s in enumerate(t):
        D = momentum_rate(trig, pose, s)
        A = structure(trig, q[i])
        need = D - gravity(trig, q[i]) - W[i]
        np.testing.assert_allclose(A @ mt.result.tensions_N[i], need, atol=2e-4)
        np.testing.assert_allclose(mt.result.tensions_N[i], controller(A, need, trig.tmin, trig.tmax),
                                   atol=1e-3)  # fmt: skip
    # the inertia really matters here: without it the tensions differ by more than 0.01 N
    still = motion_tensions(rig, Motion(q, 0 * qd, 0 * qdd), W, "exact")
    assert np.abs(still.result.tensions_N - mt.result.tensions_N).max() > 0.01
