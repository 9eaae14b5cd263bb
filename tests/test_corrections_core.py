"""Zero drift, wall corrections and repeatability against hand calculations and simple truths."""

from __future__ import annotations

import statistics

import numpy as np
import pytest

from cdpr.analysis.corrections import (
    WallParameters,
    repeatability,
    wall_corrections,
    zero_drift,
)
from cdpr.analysis.errors import InputError

S = 1_000_000_000


def test_linear_drift_is_recovered_and_sigma_by_hand() -> None:
    rate = np.array([0.002, -0.001, 0.0, 0.0005])  # N/s per cable
    z0 = np.array([1.0, -2.0, 0.5, 3.0])
    zero_t = np.array([0, 100, 200]) * S
    zeros = z0 + rate * (zero_t[:, None] / S)
    t = np.array([10, 50, 150, 199]) * S
    d = zero_drift(t, zero_t, zeros, 0.02)
    np.testing.assert_allclose(d.drift_N, rate * np.array([10, 50, 150, 199])[:, None], atol=1e-12)
    # t = 50 s: drift = 0.5 (z1 - z0): sigma = 0.5 * sqrt(2) * 0.02 = 0.0141421
    assert d.sigma_N[1, 0] == pytest.approx(0.0141421, rel=1e-5)
    # t = 150 s: drift = 0.5 z1 + 0.5 z2 - z0: sigma = 0.02 * sqrt(0.25 + 0.25 + 1) = 0.0244949
    assert d.sigma_N[2, 0] == pytest.approx(0.0244949, rel=1e-5)
    assert not d.no_closing_zero.any() and d.record.flags == ()


def test_missing_closing_zero_is_flagged() -> None:
    zero_t = np.array([0, 100]) * S
    zeros = np.array([[0.0, 0.0], [0.1, -0.1]])
    d = zero_drift(np.array([50, 150]) * S, zero_t, zeros, np.array([0.01, 0.01]))
    assert d.no_closing_zero.tolist() == [False, True]
    assert "no_closing_zero" in d.record.flags
    np.testing.assert_allclose(d.drift_N[1], [0.1, -0.1])  # held, and said so
    with pytest.raises(InputError, match="zero_T_N"):
        zero_drift([0], zero_t, np.zeros((3, 2)), 0.01)


def _closed_case() -> WallParameters:
    return WallParameters(
        kind="closed",
        area_m2=0.68,
        delta=0.125,
        tau1=0.88,
        tau2=0.1,
        body_volume_m3=6.0e-4,
        body_K3=0.93,
        wing_volume_m3=0.0,
        wing_K1=0.0,
        reference_area_m2=0.01,
        lift_slope_per_rad=4.0,
    )


def test_closed_section_against_hand_calculation() -> None:
    # Hand calculation, Barlow/Rae/Pope ch. 10, C = 0.68 m^2, S = 0.01 m^2:
    #   C^1.5 = 0.560742; eps_sb = 0.93 * 0.88 * 6.0e-4 / 0.560742 = 8.75696e-4
    #   eps_wb = S/(4C) CD = 0.01/2.72 * 0.05 = 1.838235e-4; q ratio = (1.00105952)^2 = 1.00212016
    #   S/C = 0.01470588; d_alpha_w = 0.125 * 0.01470588 * 0.6 = 1.102941e-3 rad
    #   dCD_i = 0.125 * 0.01470588 * 0.36 = 6.617647e-4
    #   d_alpha_sc = 0.1 * 1.102941e-3 = 1.102941e-4; dCL_sc = -4 * 1.102941e-4 = -4.411765e-4
    #   dCm_sc = +1.102941e-4
    #   alpha = 0.1 + 1.102941e-3 + 1.102941e-4 = 0.10121324
    #   CL = 0.6/1.00212016 - 4.411765e-4 = 0.59828942
    #   CD = 0.05/1.00212016 + 6.617647e-4 = 0.05055598
    #   Cm = -0.02/1.00212016 + 1.102941e-4 = -0.01984739
    w = wall_corrections(_closed_case(), [0.1], [0.6], [0.05], [-0.02])
    assert w.eps_solid[0] == pytest.approx(8.75696e-4, rel=1e-5)
    assert w.eps_wake[0] == pytest.approx(1.838235e-4, rel=1e-6)
    assert w.q_ratio[0] == pytest.approx(1.00212016, rel=1e-8)
    assert w.aoa_rad[0] == pytest.approx(0.10121324, rel=1e-7)
    assert w.cl[0] == pytest.approx(0.59828942, rel=1e-7)
    assert w.cd[0] == pytest.approx(0.05055598, rel=1e-6)
    assert w.cm[0] == pytest.approx(-0.01984739, rel=1e-6)
    assert "Barlow" in w.record.source


def test_open_jet_signs() -> None:
    p = _closed_case()
    o = WallParameters(**{**p.__dict__, "kind": "open_jet", "delta": -0.125})
    w = wall_corrections(o, [0.1, 0.0], [0.6, 0.0], [0.05, 0.02], [0.0, 0.0])
    assert w.eps_solid[0] < 0 and w.eps_wake[0] == 0.0
    assert w.delta_aoa_rad[0] < 0 and w.delta_aoa_rad[1] == 0.0
    with pytest.raises(InputError, match="kind"):
        WallParameters(**{**p.__dict__, "kind": "slotted"})


def test_repeatability_against_statistics_module() -> None:
    rng = np.random.default_rng(3)
    group = np.repeat(np.arange(12), 4)
    truth = np.repeat(rng.normal(size=(12, 2)), 4, axis=0)
    values = truth + rng.normal(scale=[0.01, 0.002], size=(48, 2))
    r = repeatability(group, values, np.array([0.01, 0.002]) * np.ones((48, 2)))
    pooled = [
        np.sqrt(sum(statistics.variance(values[group == g, k]) * 3 for g in range(12)) / (12 * 3))
        for k in range(2)
    ]
    np.testing.assert_allclose(r.sigma_repeat, pooled, rtol=1e-12)
    assert r.dof == 36 and not r.disagree.any()
    r_bad = repeatability(group, values, np.array([0.003, 0.002]) * np.ones((48, 2)))
    assert r_bad.disagree.tolist() == [True, False]
    assert r_bad.record.flags == ("repeatability_disagrees",)
