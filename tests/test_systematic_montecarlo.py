"""The systematic terms against a Monte Carlo over the calibrations, the geometry and the tunnel
instruments (issue 21 item 5).

The world is written again here (``tests/_lab_physics.py``: its own structure matrix, gravity and
the controller's tension distribution; ``tests/truth_rig.py``: the aerodynamic load), so an error in
cdpr's statics shows up as a disagreement.  Each draw is one campaign on the flat prototype rig:

- the rig's true anchors and attachment points are the rig file's plus errors of the stated σ;
- each load cell is calibrated again from dead weights (11 loads to 250 N, 0.3 N of reading noise):
  its fitted offset and gain and their covariance come from ``fit_load_cell``;
- the balance's interaction matrix is fitted again from 36 check loads with load-cell noise on
  the check-load readings (``check_loads``, on the nominal geometry: the two sources independent,
  as the σ budget assumes);
- the instruments read airspeed, static pressure, temperature and humidity with errors of their
  stated σ (one bias per draw, as an instrument's calibration error is);
- each point's tension means carry their own noise (25 samples of 0.02 N; sample covariance, 24
  degrees of freedom): the random part.

The truth is the aerodynamic load the draw's world applied (not the window mean).  The reduction is
cdpr's (structure matrix, tare or absolute method, the interaction matrix, the coefficient map); the
predictions are the functions under test evaluated at the *measured* values, as the core would.
The coefficient map is cdpr's for the truth too: what is tested is the error of q and the wrench,
not the axes (tested in test_aero_axes.py).
"""

from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path

import numpy as np
import pytest
from _lab_physics import LabRig, distribute
from _lab_physics import gravity_wrench as lab_gravity
from _lab_physics import structure_matrix as lab_A
from truth_rig import aero_wrench

from cdpr.analysis.aero import coefficient_matrix
from cdpr.analysis.balance_model import apply_balance_model
from cdpr.analysis.dynamics import gravity_wrench
from cdpr.analysis.flow import air_density
from cdpr.analysis.kinematics import structure_matrix_at
from cdpr.analysis.rotations import rotation_from_euler
from cdpr.analysis.systematic import (
    InstrumentAccuracy,
    flow_coefficient_covariance,
    geometry_covariance,
    interaction_covariance,
    loadcell_calibration_covariance,
    loadcell_sd_from_fit,
    systematic_wrench_covariance,
)
from cdpr.analysis.uncertainty import coverage_factor, welch_satterthwaite
from cdpr.calibration.balance_fit import check_loads, fit_load_cell
from cdpr.daq.schema import rig_from_mapping

ROOT = Path(__file__).resolve().parents[1]
RIG_FILE = ROOT / "data_samples" / "flat_experiment2.toml"

N_DRAWS = 300
ANCHOR_SD = 0.5e-3  # m per coordinate
ATTACH_SD = 0.2e-3
CAL_LOADS_N = np.linspace(0.0, 250.0, 11)
CAL_NOISE_N = 0.3
GAIN = 5e-5  # N/count, the nominal
CHECK_NOISE_N = 0.05  # load-cell noise of each check-load reading
SAMPLE_NOISE_N = 0.02
N_SAMPLES = 25
ACC = InstrumentAccuracy(
    airspeed_sd_mps=0.05,
    airspeed_rel_sd=0.004,
    static_pressure_sd_Pa=60.0,
    temperature_sd_K=0.3,
    relative_humidity_sd=0.02,
)
P_TRUE, T_TRUE, RH_TRUE = 98_000.0, 295.0, 0.5
AREA, SPAN, CHORD = 0.2441 * 0.0815, 0.2441, 0.0815


def _points(lab: LabRig):
    """Poses, kinds and speeds: four tares (one per aoa), 12 wind-on points at them (tare method),
    two wind-on points without a tare (absolute method)."""
    home = lab.reference_pose[:3]
    aoas = np.deg2rad([-4.0, 0.0, 4.0, 8.0])
    rows = [("tare", a, 0.0) for a in aoas]
    rows += [("wind_on", a, v) for v in (17.27, 25.51, 41.42) for a in aoas]
    rows += [("absolute", np.deg2rad(2.0), 41.42), ("absolute", np.deg2rad(-2.0), 25.51)]
    q = np.array([np.concatenate([home, [0.0, a, 0.0]]) for _, a, _ in rows])
    tare = np.array([-1] * 4 + [i % 4 for i in range(12)] + [-1, -1])
    return q, [r[0] for r in rows], np.array([r[2] for r in rows]), tare


def _check_load_set(lab: LabRig, rng: np.random.Generator):
    """36 check loads at three attitudes with a wind-off tare each: exact tensions (nominal
    geometry), applied wrenches."""
    home = lab.reference_pose[:3]
    poses, applied = [], []
    for a in np.deg2rad([-5.0, 0.0, 5.0]):
        q = np.concatenate([home, [0.0, a, 0.0]])
        W = rng.normal(0, 1, (12, 6)) * np.array([3.0, 2.0, 6.0, 0.05, 0.2, 0.05])
        poses += [q] * 12
        applied.append(W)
    q = np.array(poses)
    W = np.concatenate(applied)
    A = lab_A(lab, q)
    G = lab_gravity(lab, q)
    T0, _ = distribute(A, -G, lab.t_min_N, lab.t_max_N)
    Tw, _ = distribute(A, -G - W, lab.t_min_N, lab.t_max_N)
    return q, W, T0, Tw


@pytest.fixture(scope="module")
def campaign():
    rng = np.random.default_rng(21)
    lab = LabRig.from_toml(RIG_FILE)
    doc = tomllib.loads(RIG_FILE.read_text())
    doc["uncertainty"] = {"anchor_sd_m": ANCHOR_SD, "attach_sd_m": ATTACH_SD}
    rig = rig_from_mapping(doc, str(RIG_FILE))
    q, kind, V_true, tare = _points(lab)
    s, m = len(q), lab.m
    wind = np.array([k != "tare" for k in kind])
    rho_true = float(air_density(P_TRUE, T_TRUE, RH_TRUE))
    W_true = np.array(
        [aero_wrench(q[i, 4], V_true[i], rho_true) if wind[i] else np.zeros(6) for i in range(s)]
    )
    G = lab_gravity(lab, q)
    R = rotation_from_euler(q[:, 3:])
    A_nom = structure_matrix_at(rig.anchors_O_m, rig.attach_P_m, q)
    G_nom = gravity_wrench(rig.mass_kg, rig.com_P_m, R, rig.gravity_O_mps2)
    cq, cW, cT0, cTw = _check_load_set(lab, rng)
    cA = structure_matrix_at(rig.anchors_O_m, rig.attach_P_m, cq)
    T_nom, _ = distribute(lab_A(lab, q), -G - W_true, lab.t_min_N, lab.t_max_N)
    q_true = 0.5 * rho_true * V_true**2
    use = wind  # points with a recovered wrench and coefficients
    Kc = np.zeros((s, 6, 6))
    Kc[use] = coefficient_matrix(R[use], q_true[use], AREA, SPAN, CHORD)
    C_true = np.einsum("sij,sj->si", Kc, W_true)

    out = {k: [] for k in ("e_sys", "e_tot", "pred_sys", "u_r", "nu_r", "u_s", "nu_s")}
    src = {k: ([], []) for k in ("geometry", "loadcell", "interaction", "flow")}
    for _ in range(N_DRAWS):
        # --- the draw's world
        b = lab.anchors_O_m + rng.normal(0, ANCHOR_SD, (m, 3))
        pp = lab.attach_P_m + rng.normal(0, ATTACH_SD, (m, 3))
        world = dataclasses.replace(lab, anchors_O_m=b, attach_P_m=pp)
        T_true, _ = distribute(lab_A(world, q), -G - W_true, lab.t_min_N, lab.t_max_N)
        g_true = GAIN * (1 + rng.normal(0, 0.02, m))
        o_true = rng.normal(0, 5000.0, m)
        fits = []
        for c in range(m):
            counts = CAL_LOADS_N / g_true[c] + o_true[c]
            counts += rng.normal(0, CAL_NOISE_N / g_true[c], counts.size)
            fits.append(fit_load_cell(CAL_LOADS_N, counts))
        g_hat = np.array([f.gain_N_per_count for f in fits])
        o_hat = np.array([f.offset_counts for f in fits])
        lc = loadcell_sd_from_fit(
            g_hat,
            [f.sd_offset_counts for f in fits],
            [f.sd_gain_N_per_count for f in fits],
            [f.corr_offset_gain for f in fits],
            [f.n_points for f in fits],
        )
        noise0 = rng.normal(0, CHECK_NOISE_N, cT0.shape)
        noisew = rng.normal(0, CHECK_NOISE_N, cTw.shape)
        rec = np.einsum("sij,sj->si", cA, (cT0 + noise0) - (cTw + noisew))
        cl = check_loads(rec, cW)
        K = cl.interaction
        dV_rel, dV = rng.normal(0, ACC.airspeed_rel_sd), rng.normal(0, ACC.airspeed_sd_mps)
        V_meas = V_true * (1 + dV_rel) + dV
        p_meas = P_TRUE + rng.normal(0, ACC.static_pressure_sd_Pa)
        TK_meas = T_TRUE + rng.normal(0, ACC.temperature_sd_K)
        rh_meas = RH_TRUE + rng.normal(0, ACC.relative_humidity_sd)
        rho_meas = float(air_density(p_meas, TK_meas, rh_meas))
        q_meas = 0.5 * rho_meas * V_meas**2

        # --- the readings: counts of the true tensions, read with the fitted calibration
        counts_exact = T_true / g_true + o_true
        noise = rng.normal(0, SAMPLE_NOISE_N, (s, N_SAMPLES, m))
        counts_mean = counts_exact + noise.mean(axis=1) / g_true
        cov_mean = (
            np.einsum(
                "snk,snl->skl",
                noise - noise.mean(1, keepdims=True),
                noise - noise.mean(1, keepdims=True),
            )
            / (N_SAMPLES - 1)
            / N_SAMPLES
        )
        T_meas = (counts_mean - o_hat) * g_hat
        T_nf = (counts_exact - o_hat) * g_hat

        def reduce(Tm: np.ndarray, K: np.ndarray, qd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            W = np.full((s, 6), np.nan)
            t = tare >= 0
            W[t] = np.einsum("sij,sj->si", A_nom[t], Tm[tare[t]] - Tm[t])
            a = np.array([k == "absolute" for k in kind])
            W[a] = -np.einsum("sij,sj->si", A_nom[a], Tm[a]) - G_nom[a]
            Wc = np.full((s, 6), np.nan)
            Wc[use] = apply_balance_model(W[use], K)[0]
            Kq = np.zeros((s, 6, 6))
            Kq[use] = coefficient_matrix(R[use], qd[use], AREA, SPAN, CHORD)
            return Wc, np.einsum("sij,sj->si", Kq, Wc)

        Wc_nf, C_nf = reduce(T_nf, K, q_meas)
        Wc, C = reduce(T_meas, K, q_meas)
        W_uncorrected = np.full((s, 6), np.nan)
        W_uncorrected[use] = np.linalg.solve(K, Wc[use].T).T

        # --- the predictions at the measured values
        sw = systematic_wrench_covariance(rig, q, T_meas, tare, W_uncorrected, lc, cl.fit, K, None)
        _, J = apply_balance_model(np.nan_to_num(W_uncorrected), K)
        terms = {k: J @ v @ np.swapaxes(J, 1, 2) for k, v in sw.terms.items()}  # the balance stage
        Kq = np.zeros((s, 6, 6))
        Kq[use] = coefficient_matrix(R[use], q_meas[use], AREA, SPAN, CHORD)
        fl = flow_coefficient_covariance(C, V_meas, rho_meas, p_meas, TK_meas, rh_meas, ACC)
        # random: the tension means' sample covariance (both readings of a tared point)
        Ct = cov_mean.copy()
        t = tare >= 0
        Ct[t] = cov_mean[t] + cov_mean[tare[t]]
        rand_w = J @ A_nom @ Ct @ np.swapaxes(A_nom, 1, 2) @ np.swapaxes(J, 1, 2)
        # the random part's dof: Welch–Satterthwaite over the two readings (24 dof each)
        Aw = J @ A_nom
        v_on = np.einsum("sij,sjk,sik->si", Aw, cov_mean, Aw)
        v_off = np.where(
            t[:, None], np.einsum("sij,sjk,sik->si", Aw, cov_mean[np.maximum(tare, 0)], Aw), 0.0
        )
        nu_rw = welch_satterthwaite(np.stack([v_on, v_off], -1), N_SAMPLES - 1.0)
        Mc = Kq @ J @ A_nom
        c_on = np.einsum("sij,sjk,sik->si", Mc, cov_mean, Mc)
        c_off = np.where(
            t[:, None], np.einsum("sij,sjk,sik->si", Mc, cov_mean[np.maximum(tare, 0)], Mc), 0.0
        )
        nu_rc = welch_satterthwaite(np.stack([c_on, c_off], -1), N_SAMPLES - 1.0)

        def diag(c: np.ndarray) -> np.ndarray:
            return np.diagonal(c, axis1=1, axis2=2)

        parts_w = [diag(v) for v in terms.values()]
        parts_c = [diag(Kq @ v @ np.swapaxes(Kq, 1, 2)) for v in terms.values()] + [diag(fl.cov)]
        nus = [sw.dof[k] for k in terms] + [np.inf]
        var_sw, var_sc = sum(parts_w), sum(parts_c)
        nu_sw = welch_satterthwaite(np.stack(parts_w, -1), np.array(nus[:-1]))
        nu_sc = welch_satterthwaite(np.stack(parts_c, -1), np.array(nus))
        out["e_sys"].append(np.concatenate([Wc_nf - W_true, C_nf - C_true], axis=1))
        out["e_tot"].append(np.concatenate([Wc - W_true, C - C_true], axis=1))
        out["pred_sys"].append(np.concatenate([var_sw, var_sc], axis=1))
        out["u_r"].append(
            np.sqrt(
                np.concatenate([diag(rand_w), diag(Kq @ rand_w @ np.swapaxes(Kq, 1, 2))], axis=1)
            )
        )
        out["nu_r"].append(np.concatenate([nu_rw, nu_rc], axis=1))
        out["u_s"].append(np.sqrt(np.concatenate([var_sw, var_sc], axis=1)))
        out["nu_s"].append(np.concatenate([nu_sw, nu_sc], axis=1))

        # --- each source alone (the others exact), against its own prediction
        A_world = lab_A(world, q)
        Wg = np.full((s, 6), np.nan)
        Wg[t] = np.einsum("sij,sj->si", A_nom[t], T_true[tare[t]] - T_true[t])
        a = np.array([k == "absolute" for k in kind])
        Wg[a] = -np.einsum("sij,sj->si", A_nom[a], T_true[a]) - G_nom[a]
        assert np.allclose(np.einsum("sij,sj->si", A_world, T_true), -G - W_true, atol=1e-8)
        src["geometry"][0].append(Wg - W_true)
        Tt = np.where(t[:, None], T_true[np.maximum(tare, 0)], 0.0)
        src["geometry"][1].append(
            diag(
                geometry_covariance(
                    rig.anchors_O_m, rig.attach_P_m, ANCHOR_SD, ATTACH_SD, q, T_true, q, Tt
                )
            )
        )
        Tl = ((T_nom / g_true + o_true) - o_hat) * g_hat  # nominal geometry, fitted calibration
        Wl = np.full((s, 6), np.nan)
        Wl[t] = np.einsum("sij,sj->si", A_nom[t], Tl[tare[t]] - Tl[t])
        Wl[a] = -np.einsum("sij,sj->si", A_nom[a], Tl[a]) - G_nom[a]
        src["loadcell"][0].append(Wl - W_true)
        At = np.where(t[:, None, None], A_nom[np.maximum(tare, 0)], 0.0)
        Tlt = np.where(t[:, None], Tl[np.maximum(tare, 0)], 0.0)
        src["loadcell"][1].append(diag(loadcell_calibration_covariance(A_nom, Tl, lc, At, Tlt)))
        src["interaction"][0].append(W_true @ K.T - W_true)
        src["interaction"][1].append(diag(interaction_covariance(W_true, cl.fit)))
        C_flow = np.einsum("sij,sj->si", Kq, W_true)
        src["flow"][0].append(C_flow - C_true)
        fl1 = flow_coefficient_covariance(C_flow, V_meas, rho_meas, p_meas, TK_meas, rh_meas, ACC)
        src["flow"][1].append(diag(fl1.cov))
    res = {k: np.array(v) for k, v in out.items()}
    res["sources"] = {k: (np.array(e), np.array(p)) for k, (e, p) in src.items()}
    res["wind"] = wind
    return res


def expanded_U95(u_r, nu_r, u_s, nu_s) -> np.ndarray:
    """``k u_c`` with k from Student's t at the Welch–Satterthwaite dof of the two parts."""
    nu = welch_satterthwaite(np.stack([u_r**2, u_s**2], -1), np.stack([nu_r, nu_s], -1))
    return coverage_factor(nu) * np.hypot(u_r, u_s)


def _ratio(err: np.ndarray, var: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Observed rms error over the draws / predicted rms σ, per point and component (rows only)."""
    return np.sqrt(np.mean(err[:, rows] ** 2, axis=0) / np.mean(var[:, rows], axis=0))


@pytest.mark.parametrize("source", ["geometry", "loadcell", "interaction", "flow"])
def test_each_source_predicts_its_own_scatter(campaign, source) -> None:
    err, var = campaign["sources"][source]
    r = _ratio(err, var, campaign["wind"])
    assert np.all((r > 0.8) & (r < 1.25)), (source, np.round(r, 3))


def test_systematic_sigma_matches_the_monte_carlo_scatter(campaign) -> None:
    """All sources at once: the predicted systematic σ per point and output (6 wrench components
    at P after the interaction matrix, 6 coefficients) against the scatter of the noise-free
    recovery over the draws."""
    r = _ratio(campaign["e_sys"], campaign["pred_sys"], campaign["wind"])
    assert np.all((r > 0.8) & (r < 1.25)), np.round(r, 3)


def test_total_U95_covers_90_to_99_percent(campaign) -> None:
    w = campaign["wind"]
    U = expanded_U95(
        campaign["u_r"][:, w], campaign["nu_r"][:, w], campaign["u_s"][:, w], campaign["nu_s"][:, w]
    )
    inside = np.abs(campaign["e_tot"][:, w]) <= U
    overall = inside.mean()
    per_output = inside.mean(axis=(0, 1))
    assert 0.90 <= overall <= 0.99, overall
    assert np.all(per_output >= 0.85), per_output
    # the systematic part matters: without it the intervals would cover far less
    U_r = coverage_factor(campaign["nu_r"][:, w]) * campaign["u_r"][:, w]
    assert (np.abs(campaign["e_tot"][:, w]) <= U_r).mean() < 0.85
