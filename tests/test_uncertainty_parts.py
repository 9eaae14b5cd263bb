"""Random and systematic parts, degrees of freedom and U95 (GUM), and one covariance for a point,
its tare and the zeros they share — against hand derivations and a Monte Carlo written here."""

from __future__ import annotations

import numpy as np
import pytest

from cdpr.analysis.corrections import repeatability
from cdpr.analysis.reduction import POSE, WRENCH, new_points, run_stages
from cdpr.analysis.rigs import paper_rigs
from cdpr.analysis.stages import Corrections, ReduceSettings, core_stages
from cdpr.analysis.uncertainty import coverage_factor, welch_satterthwaite

S = 1_000_000_000


def test_welch_satterthwaite_and_the_coverage_factor_by_hand() -> None:
    # GUM G.4.1: nu_eff = u^4 / sum(u_i^4 / nu_i); two equal parts, one with 4 dof, one exact:
    # (1 + 1)^2 / (1^2 / 4) = 16
    assert welch_satterthwaite([1.0, 1.0], [4.0, np.inf]) == pytest.approx(16.0)
    assert welch_satterthwaite([1.0, 2.0], [np.inf, np.inf]) == np.inf
    # three variance parts 0.5, 0.3, 0.2 with 9, 4, inf dof: 1 / (0.25/9 + 0.09/4) = 19.8895
    assert welch_satterthwaite([0.5, 0.3, 0.2], [9.0, 4.0, np.inf]) == pytest.approx(19.8895, 1e-4)
    # Student's t, two-sided 95 %: tabulated 12.706 (1), 2.228 (10), 2.042 (30); normal 1.960
    np.testing.assert_allclose(
        coverage_factor([1.0, 10.0, 30.0, np.inf]), [12.706, 2.228, 2.042, 1.960], atol=1e-3
    )


def test_repeatability_compares_the_scatter_with_the_random_sigma_at_its_level() -> None:
    """Repeats whose scatter is what the random σ says, each σ estimated from a short correlated
    window (5 dof): the F test with the σ's own degrees of freedom flags about the 5 % it claims;
    a scatter 2.5 times the random σ (an unmodelled random source) is flagged nearly always."""
    rng = np.random.default_rng(3)
    trials, nu = 400, 5.0
    groups = np.repeat(np.arange(6), 2)
    false_alarm = power = 0
    for _ in range(trials):
        sd_est = np.sqrt(rng.chisquare(nu, groups.size) / nu)[:, None]  # truth 1
        dof = np.full_like(sd_est, nu)
        x = rng.normal(0.0, 1.0, groups.size)[:, None]
        false_alarm += bool(repeatability(groups, x, sd_est, dof_propagated=dof).disagree[0])
        y = rng.normal(0.0, 2.5, groups.size)[:, None]
        power += bool(repeatability(groups, y, sd_est, dof_propagated=dof).disagree[0])
    assert 0.02 < false_alarm / trials < 0.09
    assert power / trials > 0.8


def _drift_run(rng: np.random.Generator, sd_N: float):
    """Zero, tare, wind-on, zero on the flat rig at one pose: raw means drawn with a known
    covariance; the truth of the wind-on point's load is what the tare and the drift remove."""
    rig = paper_rigs()["flat_optimum"]
    m = rig.n_cables
    kind = ["zero", "tare", "wind_on", "zero"]
    t = np.array([0.0, 10.0, 20.0, 30.0])
    base = np.full(m, 150.0)
    T = base + rng.normal(0.0, sd_N, (4, m)) + 0.01 * t[:, None]  # a drift of 0.01 N/s
    T[2] += 1.0  # the wind-on point's extra load
    pose = np.concatenate([rig.reference_position_O_m, [0.0, 0.0, 0.0]])
    pts = new_points(
        kind=kind,
        start_ns=(t * S).astype(np.int64),
        tension_N=T,
        tension_cov_N2=np.broadcast_to(np.eye(m) * sd_N**2, (4, m, m)),
        **{POSE: np.tile(pose, (4, 1)), "pose_cov_O_m_rad": np.zeros((4, 6, 6))},
        airspeed_mps=np.array([0.0, 0.0, 20.0, 0.0]),
        density_kgpm3=np.full(4, 1.2),
    )
    return rig, pts


def test_a_point_its_tare_and_their_shared_zeros_are_one_covariance() -> None:
    """The wind-on point (t = 20 s) and its tare (t = 10 s) both have the drift interpolated from
    the same two zeros: in their difference most of it cancels.  The load-cell σ of the wrench
    must match the scatter of the estimates over a Monte Carlo of the raw means (before: the drift
    σ was added to both as if independent, 1.2x too wide on white noise)."""
    sd = 0.05
    rng = np.random.default_rng(8)
    W, sdW = [], None
    for _ in range(400):
        rig, pts = _drift_run(rng, sd)
        settings = ReduceSettings(fit_weight_model=False)
        out = run_stages(pts, core_stages(rig, None, settings, corrections=Corrections()))
        W.append(out[WRENCH][2])
        sdW = np.sqrt(np.diagonal(out.cov_terms["load_cells"][2]))
    scatter = np.std(np.array(W), axis=0, ddof=1)
    # the drift (0.01 N/s) is removed: the mean error is within the MC's noise
    np.testing.assert_allclose(sdW, scatter, rtol=0.12)
