"""The σ of a ringing platform's mean inertia wrench over a point (issue 21, the narrow-band mode at
the rig's lowest mode): ``M (v_end - v_start) / T``, which no zero-frequency spectrum of the
tensions sees.  The expected numbers come from a hand derivation (a point mass) and from a
narrow-band yaw oscillation generated here (an AR(2) resonance, scipy's lfilter), whose window
means of the acceleration are computed from the motion itself, not from the code under test."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import lfilter

from cdpr.analysis.dynamics import mean_inertia_covariance
from cdpr.analysis.point_inputs import pose_rate_variance


def test_a_point_mass_by_hand() -> None:
    """A 2 kg point mass at P, at rest attitude: the mean force over T = 2 s has the variance
    m^2 * 2 Var(v) / T^2 per axis; the rotations carry I_ii^2 * 2 Var(omega) / T^2."""
    I = np.diag([0.01, 0.02, 0.03])
    rv = np.array([1e-4, 4e-4, 9e-4, 1e-2, 2e-2, 3e-2])
    C = mean_inertia_covariance(2.0, [0, 0, 0], I, np.zeros(6), rv, 2.0)
    expect = np.diag(np.concatenate([4.0 * 2 * rv[:3] / 4.0, np.diag(I) ** 2 * 2 * rv[3:] / 4.0]))
    assert C == pytest.approx(expect, rel=1e-9, abs=1e-15)
    # batched over points, each window its own length
    Cb = mean_inertia_covariance(2.0, [0, 0, 0], I, np.zeros((3, 6)), np.tile(rv, (3, 1)),
                                 np.array([1.0, 2.0, 4.0]))  # fmt: skip
    assert Cb[0] == pytest.approx(4 * expect) and Cb[2] == pytest.approx(expect / 4)


def _ringing_yaw(rng: np.random.Generator, n: int, f0: float, Q: float, dt: float) -> np.ndarray:
    """A lightly damped resonance driven by white noise (AR(2) with poles at f0, damping 1/2Q)."""
    r = np.exp(-np.pi * f0 * dt / Q)
    th = 2 * np.pi * f0 * dt
    x = lfilter([1.0], [1.0, -2 * r * np.cos(th), r * r], rng.standard_normal(n + 5000))[5000:]
    return 0.004 * x / x.std()  # about 0.23 deg rms


def test_the_window_mean_of_a_ringing_mode_is_covered() -> None:
    """A 9 Hz yaw mode (Q 30) seen by a 100 Hz camera with 0.01 deg of noise: over 3 s windows
    the spread of the mean yaw acceleration (from the motion at 1 kHz: the rate at the window's
    ends) matches the σ from the camera's frames within 20 %."""
    rng = np.random.default_rng(3)
    dt, T_w, n_win = 1e-3, 3.0, 150
    n = int(T_w / dt)
    cam_sd = np.radians(0.01)
    mean_acc, sd_pred = [], []
    for _ in range(n_win):
        yaw = _ringing_yaw(rng, n + 1, 9.0, 30.0, dt)
        rate = np.gradient(yaw, dt)
        mean_acc.append((rate[-1] - rate[0]) / T_w)
        frames = np.arange(0, n + 1, 10)  # 100 Hz
        q = np.zeros((frames.size, 6))
        q[:, 5] = yaw[frames] + rng.normal(0, cam_sd, frames.size)
        t_ns = (frames * 1_000_000).astype(np.int64)
        fv = np.full((1, 6), cam_sd**2)
        rv = pose_rate_variance(t_ns, q, np.zeros(frames.size, bool), [(0, frames.size)], fv)
        sd_pred.append(np.sqrt(2 * rv[0, 5]) / T_w)
    ratio = np.std(mean_acc) / np.sqrt(np.mean(np.square(sd_pred)))
    assert 0.8 < ratio < 1.2, ratio
    z = np.array(mean_acc) / np.array(sd_pred)
    assert 0.9 <= np.mean(np.abs(z) <= 1.96) <= 0.99


def test_camera_noise_alone_gives_no_motion() -> None:
    """A platform at rest: the frames' differences are the camera's noise only, which is taken
    out (what is left is the estimate's own scatter, a small fraction of the noise's)."""
    rng = np.random.default_rng(4)
    k = 300
    sd = np.array([5e-5, 5e-5, 5e-5, 1.7e-4, 1.7e-4, 1.7e-4])
    q = rng.normal(0, 1, (k, 6)) * sd
    t_ns = np.arange(k, dtype=np.int64) * 10_000_000
    rv = pose_rate_variance(t_ns, q, np.zeros(k, bool), [(0, k)], (sd**2)[None])
    noise_rate_var = 2 * sd**2 / 0.01**2
    assert np.all(rv[0] < 0.25 * noise_rate_var)
    # a window with fewer than two usable differences has no estimate (NaN), not zero
    bad = np.ones(k, bool)
    assert np.isnan(pose_rate_variance(t_ns, q, bad, [(0, k)], (sd**2)[None])).all()


def test_windows_without_frames_yet_have_no_estimate() -> None:
    """On-line, a point's window may lie past the last frame received so far (or hold one):
    NaN, not an error."""
    t_ns = np.arange(5, dtype=np.int64) * 10_000_000
    q = np.zeros((5, 6))
    fv = np.full((3, 6), 1e-8)
    rv = pose_rate_variance(t_ns, q, np.zeros(5, bool), [(0, 5), (4, 5), (5, 5)], fv)
    assert np.isfinite(rv[0]).all() and np.isnan(rv[1:]).all()
