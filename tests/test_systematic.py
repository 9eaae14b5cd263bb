"""The systematic terms by hand, where their numbers come from (calibration files, the rig file,
the test matrix, balance.json), Welch–Satterthwaite against the GUM's own example, and the stages.

The Monte Carlo over calibrations, geometry and instruments is in
tests/test_systematic_montecarlo.py."""

from __future__ import annotations

import json
import math
import tomllib
from pathlib import Path

import numpy as np
import pytest
from _lab_physics import LabRig
from _lab_physics import structure_matrix as lab_A
from truth_rig import alpha_sweep

from cdpr.analysis import systematic_stages as ss
from cdpr.analysis.aero import ModelGeometry, coefficient_matrix
from cdpr.analysis.balance import points_from_events, sample_mask
from cdpr.analysis.errors import ConfigError
from cdpr.analysis.point_inputs import points_from_samples
from cdpr.analysis.reduction import run_stages
from cdpr.analysis.rig import Rig, rig_to_mapping
from cdpr.analysis.rotations import rotation_from_euler, skew
from cdpr.analysis.stages import (
    axes_stage,
    balance_interaction,
    coefficients_stage,
    structure_matrix_stage,
    uncertainty_stage,
    weight_model_stage,
    weight_tare_stage,
)
from cdpr.analysis.systematic import (
    INSTRUMENT_KEYS,
    BalanceFitCovariance,
    InstrumentAccuracy,
    LoadCellCalibrationSd,
    default_geometry_sd,
    flow_coefficient_covariance,
    geometry_covariance,
    geometry_jacobian,
    interaction_covariance,
    iso2768_medium_sd_m,
    loadcell_calibration_covariance,
    loadcell_sd_from_fit,
    rig_geometry_sd,
    systematic_wrench_covariance,
)
from cdpr.analysis.uncertainty import coverage_factor, expanded_uncertainty, welch_satterthwaite
from cdpr.calibration.balance_fit import check_loads, fit_load_cell
from cdpr.daq.loadcell import read_calibration_file
from cdpr.daq.schema import load_rig, rig_from_mapping
from cdpr.pipelines.campaign import load_test_matrix
from cdpr.pipelines.cli import main
from cdpr.pipelines.config import read_balance_calibration, read_balance_fit

ROOT = Path(__file__).resolve().parents[1]
FLAT = ROOT / "data_samples" / "flat_experiment2.toml"


def _one_cable(height: float = 0.8) -> Rig:
    """One vertical cable from P (at the origin of {P}) to an anchor ``height`` above it."""
    return Rig(
        name="one",
        cable_names=("c",),
        anchors_O_m=np.array([[0.0, 0.0, height]]),
        attach_P_m=np.zeros((1, 3)),
        mass_kg=1.0,
        com_P_m=np.zeros(3),
        inertia_P_kgm2=np.zeros((3, 3)),
        t_min_N=np.array([1.0]),
        t_max_N=np.array([500.0]),
    )


# ------------------------------------------------------------------------------------------------
# hand derivations
# ------------------------------------------------------------------------------------------------
def test_one_cable_gain_error_acts_on_the_tare_difference_only() -> None:
    """One vertical cable, A = [0, 0, 1, 0, 0, 0]^T.  Tare: W = A (T0 - Tw), a reading
    (c - o) g errs by -e_o + T e_g, so dFz = -(e_o - e_o) + (T0 - Tw) e_g: σ_Fz = |T0 - Tw| σ_g.
    Absolute: W = -A T - G, dFz = e_o - T e_g: σ² = σ_o² + T² σ_g² - 2 T ρ σ_o σ_g."""
    A = np.zeros((1, 6, 1))
    A[0, 2, 0] = 1.0
    s_o, s_g, rho = 0.2, 1e-3, -0.6
    cal = LoadCellCalibrationSd(
        np.array([[[s_o**2, rho * s_o * s_g], [rho * s_o * s_g, s_g**2]]]), np.array([9.0])
    )
    T0, Tw = 120.0, 112.5
    tare = loadcell_calibration_covariance(A, [[Tw]], cal, A, [[T0]])
    assert math.sqrt(tare[0, 2, 2]) == pytest.approx(abs(T0 - Tw) * s_g, rel=1e-12)
    assert np.count_nonzero(tare) == 1
    gain_only = LoadCellCalibrationSd(np.array([[[0.0, 0.0], [0.0, s_g**2]]]), np.array([9.0]))
    assert loadcell_calibration_covariance(A, [[Tw]], gain_only, A, [[T0]])[0, 2, 2] == (
        pytest.approx(((T0 - Tw) * s_g) ** 2, rel=1e-12)
    )
    absolute = loadcell_calibration_covariance(A, [[Tw]], cal)
    want = s_o**2 + Tw**2 * s_g**2 - 2 * Tw * rho * s_o * s_g
    assert absolute[0, 2, 2] == pytest.approx(want, rel=1e-12)
    # without the correlation: the bound 2 (σ_o² + T² σ_g²) >= any correlation's variance
    nocorr = LoadCellCalibrationSd(cal.cov * np.array([[1, 0], [0, 1]]), cal.dof, False)
    bound = loadcell_calibration_covariance(A, [[Tw]], nocorr)[0, 2, 2]
    assert bound == pytest.approx(2 * (s_o**2 + Tw**2 * s_g**2))
    assert bound >= max(s_o**2 + Tw**2 * s_g**2 + 2 * Tw * s_o * s_g * r for r in (-1, 1))


def test_one_cable_geometry_by_hand() -> None:
    """Vertical cable of length L, u = z, r = 0.  A lateral anchor error turns u by δb/L, a
    lateral attachment error by -δpp/L and gives the moment arm: with D = T0 - Tw (tare),
    dFx = D (δb_x - δpp_x)/L, dMy = -D δpp_x, dMx = D δpp_y; σ_Fz = σ_Mz = 0 to first order."""
    L, sb, sp = 0.8, 0.5e-3, 0.2e-3
    rig = _one_cable(L)
    q = np.zeros((1, 6))
    T0, Tw = 150.0, 140.0
    D = T0 - Tw
    C = geometry_covariance(rig.anchors_O_m, rig.attach_P_m, sb, sp, q, [[Tw]], q, [[T0]])[0]
    assert C[0, 0] == pytest.approx(D**2 * (sb**2 + sp**2) / L**2, rel=1e-9)
    assert C[1, 1] == pytest.approx(D**2 * (sb**2 + sp**2) / L**2, rel=1e-9)
    assert C[3, 3] == pytest.approx((D * sp) ** 2, rel=1e-9)
    assert C[4, 4] == pytest.approx((D * sp) ** 2, rel=1e-9)
    assert C[0, 4] == pytest.approx(D**2 * sp**2 / L, rel=1e-9)  # dFx dMy = (-D δpp/L)(-D δpp)
    assert C[1, 3] == pytest.approx(-(D**2) * sp**2 / L, rel=1e-9)
    assert abs(C[2, 2]) < 1e-18 and abs(C[5, 5]) < 1e-18
    # the absolute method: the whole tension turns
    Ca = geometry_covariance(rig.anchors_O_m, rig.attach_P_m, sb, sp, q, [[Tw]])[0]
    assert Ca[0, 0] == pytest.approx(Tw**2 * (sb**2 + sp**2) / L**2, rel=1e-9)


def test_geometry_jacobian_against_an_independent_structure_matrix() -> None:
    """The analytic Jacobian against central differences of the lab generator's own structure
    matrix (tests/_lab_physics.py) with each coordinate moved, at a tilted, off-centre pose."""
    import dataclasses

    lab = LabRig.from_toml(FLAT)
    rig = load_rig(FLAT)
    q = np.array([[0.52, 0.01, 0.35, 0.02, 0.06, -0.03], [0.48, -0.02, 0.37, -0.01, -0.05, 0.04]])
    T = np.array([np.linspace(80.0, 220.0, 8), np.linspace(200.0, 60.0, 8)])
    J = geometry_jacobian(rig.anchors_O_m, rig.attach_P_m, q, T)
    h = 1e-6
    for c in (0, 5):
        for k in range(6):
            w = []
            for sgn in (1.0, -1.0):
                b, pp = lab.anchors_O_m.copy(), lab.attach_P_m.copy()
                (b if k < 3 else pp)[c, k % 3] += sgn * h
                A = lab_A(dataclasses.replace(lab, anchors_O_m=b, attach_P_m=pp), q)
                w.append(-np.einsum("sij,sj->si", A, T))
            num = (w[0] - w[1]) / (2 * h)
            assert np.allclose(J[:, c, :, k], num, rtol=1e-6, atol=1e-6 * np.abs(num).max()), (c, k)


def test_interaction_covariance_is_the_regression_prediction_variance() -> None:
    """``S (x^T M x)``: one output, one regressor: var = s² w² / Σ x²."""
    S = np.diag([4.0, 1, 1, 1, 1, 1])
    M = np.diag([1 / 50.0, 1, 1, 1, 1, 1])
    fit = BalanceFitCovariance(S, M, 10.0)
    W = np.array([[3.0, 0, 0, 0, 0, 0]])
    C = interaction_covariance(W, fit)
    assert C[0, 0, 0] == pytest.approx(4.0 * 9.0 / 50.0)
    assert C[0, 1, 1] == pytest.approx(9.0 / 50.0)


def test_check_load_fit_covariance_against_repeated_calibrations() -> None:
    """The covariance ``check_loads`` reports for K against the scatter of K over 2000 repeated
    calibrations with fresh noise (the first-order fit's errors-in-variables included)."""
    rng = np.random.default_rng(3)
    W = rng.normal(0, 1, (30, 6)) * np.array([3.0, 2.0, 6.0, 0.05, 0.2, 0.05])
    K_true = np.eye(6) + rng.normal(0, 0.01, (6, 6))
    sd = np.array([0.05, 0.05, 0.05, 0.002, 0.002, 0.002])
    Ks, pred = [], []
    for _ in range(2000):
        rec = np.linalg.solve(K_true, W.T).T + rng.normal(0, 1, W.shape) * sd
        res = check_loads(rec, W)
        Ks.append(res.interaction)
        pred.append(np.einsum("ik,jl->ijkl", res.fit.residual_cov, res.fit.inverse_gram))
    Ks = np.array(Ks)
    observed = Ks.reshape(len(Ks), 36).var(axis=0)
    predicted = np.array(pred).mean(axis=0).reshape(36, 36).diagonal()
    ratio = np.sqrt(observed / predicted)
    assert np.all((ratio > 0.85) & (ratio < 1.15)), np.round(ratio.reshape(6, 6), 3)
    assert res.fit.dof == 24


def test_load_cell_fit_correlation_against_repeated_calibrations() -> None:
    """The offset-gain correlation and σ ``fit_load_cell`` reports against 4000 repeated fits."""
    rng = np.random.default_rng(4)
    load = np.linspace(20.0, 250.0, 8)
    fits = [
        fit_load_cell(load, 3000.0 + load / 5e-5 + rng.normal(0, 0.3 / 5e-5, load.size))
        for _ in range(4000)
    ]
    o = np.array([f.offset_counts for f in fits])
    g = np.array([f.gain_N_per_count for f in fits])
    assert np.corrcoef(o, g)[0, 1] == pytest.approx(
        np.mean([f.corr_offset_gain for f in fits]), abs=0.03
    )
    assert np.std(o) == pytest.approx(
        np.sqrt(np.mean([f.sd_offset_counts**2 for f in fits])), rel=0.05
    )
    assert np.std(g) == pytest.approx(
        np.sqrt(np.mean([f.sd_gain_N_per_count**2 for f in fits])), rel=0.05
    )
    # readings far from zero counts: offset and gain strongly tied (offset = -c/g)
    assert np.mean([f.corr_offset_gain for f in fits]) > 0.5


# ------------------------------------------------------------------------------------------------
# degrees of freedom and U95
# ------------------------------------------------------------------------------------------------
def test_welch_satterthwaite_gum_example_g41() -> None:
    """GUM (JCGM 100:2008) G.4.1: Y = b X1 X2 X3 from means of n = 10, 5, 15 observations with
    relative uncertainties 0.25 %, 0.57 %, 0.82 %: u_c/y = 1.03 %, nu_eff = 19.0, t95(19) = 2.09,
    U95 = 2.2 %."""
    u = np.array([0.25, 0.57, 0.82])
    nu = welch_satterthwaite(u**2, np.array([9.0, 4.0, 14.0]))
    assert float(nu) == pytest.approx(19.0, abs=0.05)
    uc = math.sqrt(float(np.sum(u**2)))
    assert uc == pytest.approx(1.03, abs=0.005)
    k = float(coverage_factor(nu))
    assert k == pytest.approx(2.09, abs=0.005)
    assert k * uc == pytest.approx(2.2, abs=0.05)


def test_fitted_calibrations_bring_their_degrees_of_freedom_to_u95() -> None:
    """``expanded_uncertainty(..., term_dof=...)``: a systematic term fitted from data counts with its
    own degrees of freedom.  One output, the wrench's Fx: random pose part 1 (inf), a fitted term
    of variance 1 with 4 dof, a stated term of variance 2: nu = 4^2 / (1/4) = 64, k = t95(64);
    without term_dof every systematic term is Type B (inf)."""
    C = {
        "pose": np.diag([1.0, 0, 0, 0, 0, 0])[None],
        "loadcell_calibration": np.diag([1.0, 0, 0, 0, 0, 0])[None],
        "rig_geometry": np.diag([2.0, 0, 0, 0, 0, 0])[None],
    }
    L = np.eye(6)[None, :1]  # the output Fx
    empty = (np.zeros((1, 0, 6, 8)), np.zeros((1, 0), np.int64), np.zeros((1, 8, 8)))
    args = (C, L, *empty[:2], empty[2], empty[2], np.full(1, 2))
    base = expanded_uncertainty(*args)
    fitted = expanded_uncertainty(
        *args, term_dof={"loadcell_calibration": 4.0, "rig_geometry": math.inf}
    )
    assert float(base.dof[0, 0]) == math.inf
    assert float(fitted.dof[0, 0]) == pytest.approx(64.0)
    assert float(fitted.k[0, 0]) == pytest.approx(1.9977, abs=1e-3)  # t_0.975(64)
    assert float(fitted.u_systematic[0, 0]) == pytest.approx(math.sqrt(3.0))
    assert float(fitted.u_random[0, 0]) == pytest.approx(1.0)
    assert float(fitted.U[0, 0]) == pytest.approx(float(fitted.k[0, 0]) * 2.0)


def test_welch_satterthwaite_coverage_by_simulation() -> None:
    """A Type A part estimated from 5 readings (4 dof) beside a smaller Type B part: k from nu_eff
    covers about 95 % (Welch–Satterthwaite is an approximation, about 1 % liberal at so few
    degrees of freedom: 93.9 % here); k = 1.96 covers 90 %."""
    rng = np.random.default_rng(7)
    n, N = 5, 40_000
    sr, sb = 1.0, 0.2
    x = rng.normal(0, sr, (N, n))
    err = x.mean(axis=1) + rng.normal(0, sb, N)
    ur = x.std(axis=1, ddof=1) / math.sqrt(n)
    nu = welch_satterthwaite(np.stack([ur**2, np.full(N, sb**2)], -1), [n - 1.0, np.inf])
    U = coverage_factor(nu) * np.hypot(ur, sb)
    cov = np.mean(np.abs(err) <= U)
    assert 0.93 <= cov <= 0.965, cov
    assert np.mean(np.abs(err) <= 1.96 * np.hypot(ur, sb)) < cov - 0.02


# ------------------------------------------------------------------------------------------------
# the instruments
# ------------------------------------------------------------------------------------------------
def test_flow_term_by_hand_dry_air() -> None:
    """Dry air: rho = p/(R T), so σ_ρ/ρ = sqrt((σ_p/p)² + (σ_T/T)²); q = rho V²/2:
    σ_q/q = sqrt((σ_ρ/ρ)² + 4 (σ_V/V)²); dC = -C σ_q/q."""
    acc = InstrumentAccuracy(0.1, 0.005, 50.0, 0.3, 0.0)
    C = np.array([[0.05, 0.01, 0.8, 0.002, -0.04, 0.001]])
    p, T, V = 99_000.0, 290.0, 30.0
    fu = flow_coefficient_covariance(C, [V], [p / (287.05287 * T)], [p], [T], [0.0], acc)
    rho_rel = math.hypot(50.0 / p, 0.3 / T)
    v_rel = math.hypot(0.1, 0.005 * V) / V
    assert fu.density_rel_sd[0] == pytest.approx(rho_rel, rel=1e-4)
    q_rel = math.sqrt(rho_rel**2 + 4 * v_rel**2)
    assert fu.q_rel_sd[0] == pytest.approx(q_rel, rel=1e-4)
    assert np.allclose(fu.cov[0], np.outer(C[0], C[0]) * q_rel**2, rtol=1e-4)


def test_flow_term_without_humidity_covers_the_unknown() -> None:
    """No hygrometer: the density is dry and its σ covers a humidity anywhere in 0..1 (1/√3 of
    the whole effect), larger than a hygrometer's 3 %."""
    acc = InstrumentAccuracy()
    args = ([[1.0] * 6], [30.0], [1.17], [100_000.0], [300.0])
    wet = flow_coefficient_covariance(*args, [0.5], acc)
    dry = flow_coefficient_covariance(*args, [np.nan], acc)
    assert dry.humidity_unknown[0] and not wet.humidity_unknown[0]
    assert dry.density_rel_sd[0] > 5 * wet.density_rel_sd[0]
    assert dry.density_rel_sd[0] == pytest.approx(0.0128 / math.sqrt(3), rel=0.1)  # e_s(27 °C)


def test_instruments_from_the_test_matrix(tmp_path: Path) -> None:
    src = (ROOT / "data_samples" / "campaign_alpha_sweep.toml").read_text()
    m0 = load_test_matrix(ROOT / "data_samples" / "campaign_alpha_sweep.toml")
    assert set(m0.instruments.defaulted) == set(INSTRUMENT_KEYS)
    f = tmp_path / "m.toml"
    for name in ("flat_experiment2.toml", "camera_virtual.json", "markers_flat_ir6.toml"):
        (tmp_path / name).write_text((ROOT / "data_samples" / name).read_text())
    f.write_text(src + "\n[instruments]\nairspeed_sd_mps = 0.08\ntemperature_sd_K = 0.1\n")
    m = load_test_matrix(f)
    assert m.instruments.airspeed_sd_mps == 0.08 and m.instruments.airspeed_rel_sd == 0.0
    assert m.instruments.temperature_sd_K == 0.1
    assert set(m.instruments.defaulted) == {"static_pressure_sd_Pa", "relative_humidity_sd"}
    for bad, key, msg in (
        ("airspeed_sd_mps = -0.1", "instruments.airspeed_sd_mps", "must be >= 0"),
        ("relative_humidity_sd = 3.0", "instruments.relative_humidity_sd", "must be <= 1"),
        ("temperature_sd_K = 'x'", "instruments.temperature_sd_K", "expected a number"),
        ("pitot_sd = 1.0", "instruments.pitot_sd", "unknown key"),
    ):
        f.write_text(src + f"\n[instruments]\n{bad}\n")
        with pytest.raises(ConfigError, match=msg) as e:
            load_test_matrix(f)
        assert e.value.key == key and "\n" not in str(e.value)


# ------------------------------------------------------------------------------------------------
# the rig geometry's σ
# ------------------------------------------------------------------------------------------------
def test_rig_geometry_sd_keys_defaults_and_errors() -> None:
    rig = load_rig(FLAT)
    g = rig_geometry_sd(rig)
    assert g.defaulted.all()
    # ISO 2768-1 m: the frame's largest coordinate 0.72 m -> ±0.8 mm, the platform's 15 mm ->
    # ±0.2 mm, rectangular
    assert np.allclose(g.anchor_sd_m, 0.8e-3 / math.sqrt(3))
    assert np.allclose(g.attach_sd_m, 0.2e-3 / math.sqrt(3))
    assert default_geometry_sd([[2.0, 0, 0]], [[0.15, 0, 0]]) == pytest.approx(
        (1.2e-3 / math.sqrt(3), 0.5e-3 / math.sqrt(3))
    )
    assert iso2768_medium_sd_m(8.0) == pytest.approx(4e-3 / math.sqrt(3))
    doc = tomllib.loads(FLAT.read_text())
    doc["uncertainty"] = {"anchor_sd_m": 1e-3, "attach_sd_m": 1e-4}
    doc["cables"][2]["anchor_sd_m"] = [2e-4, 3e-4, 4e-4]
    doc["cables"][2]["attach_sd_m"] = 5e-5
    r = rig_from_mapping(doc, "rig.toml")
    g = rig_geometry_sd(r)
    assert not g.defaulted.any()
    assert np.allclose(g.anchor_sd_m[2], [2e-4, 3e-4, 4e-4]) and np.allclose(g.anchor_sd_m[0], 1e-3)
    again = rig_from_mapping(rig_to_mapping(r), "again")  # written back per cable
    assert np.array_equal(again.anchor_sd_m, r.anchor_sd_m)
    assert np.array_equal(again.attach_sd_m, r.attach_sd_m)
    del doc["uncertainty"]
    g = rig_geometry_sd(rig_from_mapping(doc, "rig.toml"))
    assert g.defaulted.tolist() == [True, True, False] + [True] * 5
    for table, key, value, msg in (
        ("uncertainty", "anchor_sd_m", -1e-3, "must be >= 0"),
        ("uncertainty", "attach_sd_m", 0.5, "must be <= 0.1"),
        ("cable", "anchor_sd_m", [1e-3, 1e-3], "expected"),
        ("cable", "attach_sd_m", "0.001", "expected"),
    ):
        d = tomllib.loads(FLAT.read_text())
        if table == "uncertainty":
            d["uncertainty"] = {key: value}
            where = f"uncertainty.{key}"
        else:
            d["cables"][1][key] = value
            where = f"cables[1].{key}"
        with pytest.raises(ConfigError, match=msg) as e:
            rig_from_mapping(d, "rig.toml")
        assert e.value.key.startswith(where) and "\n" not in str(e.value)


def test_systematic_flags_a_defaulted_geometry_and_missing_calibration_sd() -> None:
    rig = load_rig(FLAT)
    q = np.tile(np.r_[rig.reference_position_O_m, 0, 0, 0], (3, 1))
    T = np.full((3, 8), 150.0)
    W = np.array([[1.0, 0, 2, 0, 0.01, 0], [np.nan] * 6, [0.5, 0, 1, 0, 0, 0]])
    sw = systematic_wrench_covariance(rig, q, T, [-1, -1, -1], W, None, None, np.eye(6))
    assert sw.flags["rig_geometry_sd_default"].tolist() == [True, False, True]
    assert sw.flags["loadcell_calibration_sd_not_given"].tolist() == [True, False, True]
    assert sw.flags["interaction_matrix_sd_not_given"].tolist() == [True, False, True]
    assert "loadcell_calibration" not in sw.terms and "interaction_matrix" not in sw.terms
    assert np.isnan(sw.terms["rig_geometry"][1]).all()
    assert np.all(np.diagonal(sw.terms["rig_geometry"][0]) > 0)


# ------------------------------------------------------------------------------------------------
# the files: calibration file, balance.json
# ------------------------------------------------------------------------------------------------
def _calibrate_loadcells(tmp_path: Path) -> Path:
    out = tmp_path / "lc.toml"
    rc = main(
        [
            "calibrate", "loadcells", str(ROOT / "data_samples" / "loadcell_points.csv"),
            "--rig", str(FLAT), "--out", str(out),
        ]
    )  # fmt: skip
    assert rc == 0
    return out


def test_loadcell_calibration_file_carries_its_covariance(tmp_path: Path) -> None:
    import pandas as pd

    out = _calibrate_loadcells(tmp_path)
    text = out.read_text()
    assert "corr_offset_gain" in text
    rig = load_rig(FLAT)
    f = read_calibration_file(out)
    sd = f.sd_for_cables(rig.cable_names)
    assert sd is not None and sd.correlation_given
    df = pd.read_csv(ROOT / "data_samples" / "loadcell_points.csv", comment="#")
    name = rig.cable_names[3]
    sel = df[df["channel"].astype(str).str.strip() == name]
    fit = fit_load_cell(sel["load_N"], sel["counts"])
    # (e_o, e_g): σ |g| sd_offset and sd_gain / |g|, correlated as the fit's parameters
    g = fit.gain_N_per_count
    assert math.sqrt(sd.cov[3, 0, 0]) == pytest.approx(abs(g) * fit.sd_offset_counts, rel=1e-9)
    assert math.sqrt(sd.cov[3, 1, 1]) == pytest.approx(fit.sd_gain_N_per_count / abs(g), rel=1e-9)
    assert sd.cov[3, 0, 1] / math.sqrt(sd.cov[3, 0, 0] * sd.cov[3, 1, 1]) == pytest.approx(
        fit.corr_offset_gain, rel=1e-9
    )
    assert sd.dof[3] == fit.n_points - 2
    # the cables in another order are matched by name
    rev = f.sd_for_cables(list(reversed(rig.cable_names)))
    assert rev is not None and np.array_equal(rev.cov[::-1], sd.cov)
    # a file without the fit statistics: no σ (the reduction flags it), a file without the
    # correlation: σ without it
    lines = [ln for ln in text.splitlines() if not ln.startswith(("sd_", "corr_"))]
    (tmp_path / "bare.toml").write_text("\n".join(lines) + "\n")
    assert read_calibration_file(tmp_path / "bare.toml").sd_for_cables(rig.cable_names) is None
    lines = [ln for ln in text.splitlines() if not ln.startswith("corr_")]
    (tmp_path / "old.toml").write_text("\n".join(lines) + "\n")
    old = read_calibration_file(tmp_path / "old.toml").sd_for_cables(rig.cable_names)
    assert old is not None and not old.correlation_given


@pytest.mark.parametrize(
    ("edit", "key", "msg"),
    [
        (("corr_offset_gain", "1.5"), "calibration.corr_offset_gain[0]", "correlation in"),
        (("sd_gain_N_per_count", "-1e-9"), "calibration.sd_gain_N_per_count[0]", ">= 0"),
        (("n_points", "2"), "calibration.n_points[0]", "at least 3"),
        (("sd_offset_counts", "[1.0, 2.0]"), "calibration.sd_offset_counts", "expected 8 values"),
        (("n_points", None), "calibration.n_points", "missing"),
        (("corr_offset_gain", "'x'"), "calibration.corr_offset_gain", "expected numbers"),
    ],
)
def test_bad_calibration_sd_is_one_line(tmp_path: Path, edit, key, msg) -> None:
    out = _calibrate_loadcells(tmp_path)
    lines = []
    for ln in out.read_text().splitlines():
        if ln.startswith(edit[0] + " "):
            if edit[1] is None:
                continue
            if edit[0] != "sd_offset_counts":  # the first value only
                head, _, rest = ln.partition("[")
                ln = f"{head}[{edit[1]}, {rest.split(',', 1)[1]}" if edit[1][0] != "[" else ln
                if edit[1] == "'x'":
                    ln = f"{edit[0]} = 'x'"
            else:
                ln = f"{edit[0]} = {edit[1]}"
        lines.append(ln)
    out.write_text("\n".join(lines) + "\n")
    with pytest.raises(ConfigError, match=msg) as e:
        read_calibration_file(out)
    assert e.value.key == key and "\n" not in str(e.value)


def test_balance_json_carries_the_fit_covariance(tmp_path: Path) -> None:
    out = tmp_path / "balance.json"
    rc = main(
        [
            "calibrate", "balance", str(ROOT / "data_samples" / "checkloads_flat.csv"),
            "--rig", str(ROOT / "data_samples" / "flat_optimum.toml"), "--out", str(out),
        ]
    )  # fmt: skip
    assert rc == 0
    doc = json.loads(out.read_text())
    K, second = read_balance_calibration(str(out))
    fit = read_balance_fit(str(out))
    assert isinstance(fit, BalanceFitCovariance)
    assert fit.second_order == (second is not None)
    key = doc["second_order"]["fit"] if second is not None else doc["interaction_matrix_fit"]
    assert fit.dof == key["dof"] > 0
    assert np.allclose(fit.residual_cov, key["residual_cov"])
    # the file's numbers are the fit's: the diagonal of S is the corrected residual's variance
    n = doc["n_check_loads"]
    if second is None:
        rms = np.array(doc["corrected_rms_error"])
        assert np.allclose(np.diag(fit.residual_cov), rms**2 * n / fit.dof, rtol=1e-9)
    bad = dict(doc)
    bad["interaction_matrix_fit"] = {**doc["interaction_matrix_fit"], "inverse_gram": [[1.0]]}
    bad["second_order"] = None
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    with pytest.raises(ConfigError, match="inverse_gram") as e:
        read_balance_fit(str(tmp_path / "bad.json"))
    assert e.value.key == "interaction_matrix_fit" and "\n" not in str(e.value)
    old = {k: v for k, v in doc.items() if k != "interaction_matrix_fit"}
    old["second_order"] = None
    (tmp_path / "old.json").write_text(json.dumps(old))
    assert read_balance_fit(str(tmp_path / "old.json")) is None
    assert read_balance_fit(None) is None


# ------------------------------------------------------------------------------------------------
# the stages, bound into the core
# ------------------------------------------------------------------------------------------------
GEOMETRY = ModelGeometry(area_m2=0.0199, span_m=0.2441, chord_m=0.0815)


def _points():
    sw = alpha_sweep(11)
    bits = sample_mask(sw.tensions_N)
    ranges = points_from_events(sw.t_ns, sw.start_ns, sw.stop_ns)
    pts, _ = points_from_samples(
        kind=sw.kind, ranges=ranges, t_ns=sw.t_ns, tensions_N=sw.tensions_N, mask_bits=bits,
        airspeed_mps=sw.airspeed_mps, density_kgpm3=sw.density_kgpm3, pose_t_ns=sw.pose_t_ns,
        poses=sw.poses, pose_cov=sw.pose_cov,
    )  # fmt: skip
    return pts


def test_stages_in_the_core_order(monkeypatch) -> None:
    """The two stages bound where their docstrings place them, with main's uncertainty stage after
    them: the terms appear by source, the balance stage carries the interaction term back to
    exactly its own covariance, the uncertainty stage counts them as systematic, and its function
    bound with ``term_dof`` and the instruments' part gives the budget the issue asks for."""
    import functools

    rig = load_rig(FLAT)
    pts = _points()
    rng = np.random.default_rng(5)
    K = np.eye(6) + rng.normal(0, 0.01, (6, 6))
    fit = BalanceFitCovariance(
        np.diag([1e-4] * 3 + [1e-7] * 3), np.diag([0.01] * 3 + [10.0] * 3), 30.0
    )
    lc = loadcell_sd_from_fit(np.full(8, 5e-5), 40.0, 2e-8, -0.8, 11)
    calls = []
    for fn_name in ("systematic_wrench_covariance", "flow_coefficient_covariance"):
        orig = getattr(ss, fn_name)

        def spy(*a, _orig=orig, _name=fn_name, **k):
            calls.append(_name)
            return _orig(*a, **k)

        monkeypatch.setattr(ss, fn_name, spy)
    head = [
        functools.partial(structure_matrix_stage, rig=rig),
        functools.partial(weight_model_stage, rig=rig),
        functools.partial(weight_tare_stage, rig=rig),
    ]
    systematic = functools.partial(
        ss.systematic_stage, rig=rig, loadcell=lc, balance_fit=fit, interaction=K
    )
    tail = [
        functools.partial(balance_interaction, interaction=K),
        functools.partial(axes_stage, geometry=GEOMETRY),
        functools.partial(coefficients_stage, geometry=GEOMETRY),
        functools.partial(
            ss.flow_uncertainty_stage,
            instruments=InstrumentAccuracy(defaulted=("airspeed_rel_sd",)),
        ),
        functools.partial(uncertainty_stage, geometry=GEOMETRY),
    ]
    before = run_stages(pts, [*head, systematic])
    out = run_stages(before, tail)
    plain = run_stages(pts, [*head, *tail])  # the same without the systematic terms
    # one call each in the run with the systematic stage, and the flow stage again in ``plain``
    assert calls == [
        "systematic_wrench_covariance", "flow_coefficient_covariance", "flow_coefficient_covariance"
    ]  # fmt: skip
    on = np.flatnonzero(out["kind"] == "wind_on")
    for name in ("loadcell_calibration", "rig_geometry", "interaction_matrix"):
        assert name in out.cov_terms and np.all(np.isfinite(out.cov_terms[name][on]))
    # after the balance stage the interaction term is S (x^T M x) at the uncorrected wrench
    direct = interaction_covariance(before["wrench_P_O_N_Nm"][on], fit)
    assert np.allclose(out.cov_terms["interaction_matrix"][on], direct, rtol=1e-9, atol=1e-18)
    flags = [set(out.flags[i]) for i in on]
    assert all({"rig_geometry_sd_default", "tunnel_instrument_sd_default"} <= f for f in flags)
    assert out.meta["systematic_dof"] == {
        "rig_geometry": math.inf,
        "loadcell_calibration": 9.0,
        "interaction_matrix": 30.0,
    }
    # the uncertainty stage counts the new terms as systematic, the random part unchanged
    cols = ["fx_N", "fz_N", "my_Nm", "CD", "CL", "Cm"]
    for c in cols:
        assert np.allclose(out[f"sd_random_{c}"][on], plain[f"sd_random_{c}"][on], rtol=1e-9)
        assert np.all(out[f"sd_systematic_{c}"][on] > plain[f"sd_systematic_{c}"][on])
    # bound with term_dof and the instruments' part (what the lead's binding adds)
    s = out.n
    X = np.tile(np.eye(6), (s, 1, 1))
    r = np.einsum("sij,j->si", rotation_from_euler(out["pose_O_m_rad"][:, 3:]), GEOMETRY.mrp_P_m)
    X[:, 3:, :3] = -skew(r)
    Kc = np.full((s, 6, 6), np.nan)
    Kc[on] = coefficient_matrix(
        rotation_from_euler(out["pose_O_m_rad"][on, 3:]), out["q_Pa"][on], GEOMETRY.area_m2,
        GEOMETRY.span_m, GEOMETRY.chord_m, GEOMETRY.mrp_P_m,
    )  # fmt: skip
    flow_u2 = np.diagonal(out["coefficient_cov_flow"], axis1=1, axis2=2)
    extra = np.concatenate([np.zeros((s, 6)), flow_u2], axis=1)
    m = out["tension_N"].shape[1]
    args = (
        dict(out.cov_terms), np.concatenate([X, Kc], axis=1), np.zeros((s, 0, 6, m)),
        np.zeros((s, 0), np.int64), out["tension_cov_N2"], out["tension_cov_N2"], np.full(s, 2),
    )  # fmt: skip
    eu = expanded_uncertainty(*args, extra_systematic_u2=extra, term_dof=out.meta["systematic_dof"])
    base = expanded_uncertainty(*args)
    k = 6 + 2  # CL
    assert np.allclose(
        eu.u_systematic[on, k] ** 2, base.u_systematic[on, k] ** 2 + flow_u2[on, 2], rtol=1e-9
    )
    assert np.all(eu.dof[on, :6] < base.dof[on, :6])  # the fitted calibrations' finite dof
    assert np.all(np.isfinite(eu.U[on]))
