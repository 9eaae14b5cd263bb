"""Stiffness and modes against an own finite-difference stiffness, scipy's generalized eigen-solver
and the peak of a simulated free response; the spectrum check on synthetic tensions."""

from __future__ import annotations

import numpy as np
import pytest
from _stiffness_truth import G, fd_stiffness, rigid_mass
from scipy.integrate import solve_ivp
from scipy.linalg import eigh

from cdpr.analysis.rigs import flat_rig
from cdpr.analysis.stiffness import mass_matrix, natural_modes, spectrum_check, stiffness_matrix

EA = 7.0e4


def _setup():
    rig = flat_rig(51, 28, 0.67, 0.5)
    p0 = rig.reference_position_O_m
    com = np.array([0.004, 0.0, -0.003])  # off P, so gravity's geometric term matters
    m = rig.mass_kg
    lv = rig.anchors_O_m - p0 - rig.attach_P_m
    u = lv / np.linalg.norm(lv, axis=1)[:, None]
    A = np.vstack([u.T, np.cross(rig.attach_P_m, u).T])
    Wg = np.concatenate([m * G, np.cross(com, m * G)])
    t_mid = np.full(8, 160.0)
    T0 = t_mid - np.linalg.pinv(A) @ (A @ t_mid + Wg)  # equilibrium A T0 = -G, closest to T_mid
    K_fd = fd_stiffness(rig.anchors_O_m, rig.attach_P_m, p0, T0, EA, m, com)
    M = rigid_mass(m, com, rig.inertia_P_kgm2)
    return rig, com, T0, K_fd, M


def test_stiffness_matches_finite_differences_and_scipy_modes() -> None:
    rig, com, T0, K_fd, M = _setup()
    st = stiffness_matrix(
        rig.anchors_O_m,
        rig.attach_P_m,
        rig.reference_position_O_m,
        np.eye(3),
        T0,
        EA,
        rig.mass_kg,
        com,
        G,
    )
    assert st.asymmetry < 1e-10  # symmetric at equilibrium
    np.testing.assert_allclose(st.K, K_fd, rtol=1e-5, atol=1e-5 * np.abs(K_fd).max())
    Mm = mass_matrix(rig.mass_kg, com, rig.inertia_P_kgm2, np.eye(3))
    np.testing.assert_allclose(Mm, M, atol=1e-15)
    modes = natural_modes(st.K, Mm)
    w2 = eigh(K_fd, M, eigvals_only=True)
    np.testing.assert_allclose(modes.frequencies_Hz, np.sqrt(w2) / (2 * np.pi), rtol=1e-5)
    # mode shapes: K phi = w^2 M phi, M-normalised
    phi = modes.shapes
    np.testing.assert_allclose(phi.T @ Mm @ phi, np.eye(6), atol=1e-9)
    assert not modes.unstable


def test_lowest_mode_is_the_peak_of_a_free_response() -> None:
    rig, com, T0, K_fd, M = _setup()
    st = stiffness_matrix(
        rig.anchors_O_m,
        rig.attach_P_m,
        rig.reference_position_O_m,
        np.eye(3),
        T0,
        EA,
        rig.mass_kg,
        com,
        G,
    )
    f = natural_modes(st.K, mass_matrix(rig.mass_kg, com, rig.inertia_P_kgm2, np.eye(3)))
    f1 = f.frequencies_Hz[0]
    Minv_K = np.linalg.solve(M, K_fd)
    x0 = np.array([1e-4, 0, 0, 0, 0, 0]) + np.linalg.solve(M, np.ones(6)) * 1e-6

    def rhs(_t, s):
        return np.concatenate([s[6:], -Minv_K @ s[:6]])

    fs, dur = 6.0 * f.frequencies_Hz[-1], 30.0 / f1
    t = np.arange(0, dur, 1 / fs)
    sol = solve_ivp(
        rhs,
        (0, t[-1]),
        np.concatenate([x0, np.zeros(6)]),
        t_eval=t,
        rtol=1e-8,
        atol=1e-14,
        method="DOP853",
    )
    # a weighted sum of coordinates, so every mode shows; find the lowest-frequency spectral peak
    y = sol.y[:6].T @ np.array([1.0, 1.0, 1.0, 0.05, 0.05, 0.05])
    n = 16 * t.size
    spec = np.abs(np.fft.rfft((y - y.mean()) * np.hanning(t.size), n))
    freqs = np.fft.rfftfreq(n, 1 / fs)
    peaks = np.flatnonzero((spec[1:-1] > spec[:-2]) & (spec[1:-1] > spec[2:])) + 1
    big = peaks[spec[peaks] > 0.02 * spec.max()]
    assert freqs[big[0]] == pytest.approx(f1, rel=5e-3)


def test_spectrum_check_flags() -> None:
    fs, f_mode = 1000.0, 37.0
    rng = np.random.default_rng(1)
    t = np.arange(4000) / fs
    base = 160.0 + rng.normal(scale=0.05, size=(t.size, 3))
    ringing = base + np.outer(0.5 * np.sin(2 * np.pi * 38.0 * t), [1.0, 0.0, 0.0])
    c = spectrum_check(ringing, fs, [f_mode, 80.0])
    assert c.peak_near_mode.tolist() == [True, False, False]
    assert not c.too_few_periods and c.record.flags == ("spectrum_peak_near_mode",)
    assert c.peak_Hz[0] == pytest.approx(38.0, abs=1.5)
    away = base + np.outer(0.5 * np.sin(2 * np.pi * 13.0 * t), [1.0, 1.0, 1.0])
    assert not spectrum_check(away, fs, [f_mode, 80.0]).peak_near_mode.any()
    short = spectrum_check(base[:200], fs, [f_mode])  # 0.2 s holds 7.4 periods of 37 Hz
    assert short.too_few_periods and "too_few_periods" in short.record.flags
