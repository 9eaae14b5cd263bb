"""Cable windage model against a separately written distributed-load taut-string model, and the
measured windage tare fit against a known smooth truth."""

from __future__ import annotations

import numpy as np
import pytest
from _cable_drag_truth import MU, RHO, D, string_end_force

from cdpr.analysis.errors import InputError
from cdpr.analysis.rigs import flat_rig
from cdpr.analysis.test_section import SectionGeometry, rectangle, regular_octagon
from cdpr.analysis.windage import cable_windage, evaluate_windage_tare, fit_windage_tare


def test_model_matches_own_string_solution_on_flat_optimum() -> None:
    rig = flat_rig(51, 28, 0.67, 0.5)
    side = 0.376
    apothem = side * (1 + 2**0.5) / 2
    yc, zc, x0, x1 = 0.0, 0.335, -0.0375, 1.0375
    section = SectionGeometry(x0, x1, regular_octagon(side, (yc, zc)))
    assert section.area_m2 == pytest.approx(2 * (1 + 2**0.5) * side**2, rel=1e-12)
    p = rig.reference_position_O_m + np.array([0.0, 0.01, -0.02])
    c, s_ = np.cos(0.1), np.sin(0.1)
    R = np.array([[c, 0, s_], [0, 1, 0], [-s_, 0, c]])  # pitch 0.1 rad
    T = np.linspace(60.0, 200.0, rig.n_cables)
    V = 41.42
    out = cable_windage(
        rig.anchors_O_m, rig.attach_P_m, p, R[None], T[None], V, RHO, MU, D, section
    )
    W = np.zeros(6)
    for i in range(rig.n_cables):
        start = p + R @ rig.attach_P_m[i]
        F, turn = string_end_force(start, rig.anchors_O_m[i], T[i], V, apothem, yc, zc, x0, x1)
        assert out.end_force_N[0, i] == pytest.approx(np.linalg.norm(F), rel=2e-3, abs=1e-6)
        assert out.turn_rad[0, i] == pytest.approx(turn, rel=2e-3, abs=1e-8)
        W += np.concatenate([F, np.cross(R @ rig.attach_P_m[i], F)])
    np.testing.assert_allclose(
        out.wrench_N[0], W, rtol=3e-3, atol=5e-5
    )  # wall crossings resolved to l/4000
    assert 0.1 < out.wrench_N[0, 0] < 2.0  # of the order of the estimate


def test_uniform_load_passes_half_to_the_platform() -> None:
    # one vertical cable, wholly in the flow, CD given: f = rho V^2 d CD / 2, R = f l / 2
    section = SectionGeometry(-1.0, 1.0, rectangle(2.0, 2.0))
    out = cable_windage(
        [[0.0, 0.0, 0.5]],
        [[0.0, 0.0, 0.0]],
        [[0.0, 0.0, -0.5]],
        np.eye(3)[None],
        [[100.0]],
        20.0,
        RHO,
        MU,
        D,
        section,
        drag_coefficient=[1.2],
    )
    f = 0.5 * 1.2 * 400.0 * 1e-3 * 1.2  # 0.288 N/m over 1 m
    np.testing.assert_allclose(out.wrench_N[0], [0.144, 0, 0, 0, 0, 0], atol=1e-12)
    assert out.turn_rad[0, 0] == pytest.approx(0.144 / 100.0)
    assert out.load_N_per_m[0, 0] == pytest.approx(f)
    # a cable along the flow carries no cross-flow load
    along = cable_windage(
        [[0.5, 0.0, 0.0]],
        [[0.0, 0.0, 0.0]],
        [[-0.5, 0.0, 0.0]],
        np.eye(3)[None],
        [[100.0]],
        20.0,
        RHO,
        MU,
        D,
        section,
    )
    np.testing.assert_allclose(along.wrench_N, 0.0, atol=1e-15)


def _truth_tare(v, a, b):
    q = 0.5 * 1.2 * v**2
    return np.stack(
        [q * (1e-3 + 2e-3 * a**2), q * 5e-4 * b, q * (3e-4 * a), q * 1e-5 * b, q * 2e-5 * a, 0 * a],
        axis=-1,
    )


def test_tare_fit_recovers_smooth_truth_with_honest_sigma() -> None:
    rng = np.random.default_rng(7)
    speeds = np.repeat([17.27, 25.51, 41.42], 25)
    aoa = np.tile(np.repeat(np.deg2rad([-10, -5, 0, 5, 10]), 5), 3)
    slip = np.tile(np.deg2rad([-4, -2, 0, 2, 4] * 5), 3)
    noise = 0.004
    W = _truth_tare(speeds, aoa, slip) + rng.normal(scale=noise, size=(75, 6))
    fit = fit_windage_tare(speeds * (1 + rng.uniform(-0.005, 0.005, 75)), aoa, slip, W)
    assert fit.speeds_mps.size == 3
    # 19 degrees of freedom per speed: the residual sigma lies within [0.5, 1.5] x the noise
    for f in fit.fits:
        assert np.all((np.sqrt(f.s2) > 0.5 * noise) & (np.sqrt(f.s2) < 1.5 * noise))
    a = np.deg2rad(np.linspace(-9, 9, 7))
    b = np.deg2rad(np.linspace(-3, 3, 7))
    for v in (17.27, 41.42):
        t = evaluate_windage_tare(fit, v, a, b)
        err = np.abs(t.tare_N - _truth_tare(v, a, b))
        assert np.all(err < 5 * t.sigma_N)
        assert not t.missing.any() and not t.extrapolated.any()
    t = evaluate_windage_tare(fit, [33.0, 41.42], [0.0, np.deg2rad(15)], [0.0, 0.0])
    assert t.missing.tolist() == [True, False] and np.isnan(t.tare_N[0]).all()
    assert t.extrapolated.tolist() == [False, True]
    assert set(t.record.flags) == {"windage_tare_missing", "windage_tare_extrapolated"}
    with pytest.raises(InputError, match="17.27 m/s"):
        fit_windage_tare([17.27] * 4, np.deg2rad([0, 5, 10, 15]), 0.0, np.zeros((4, 6)), 3)
