"""An angle-of-attack sweep at the paper's three speeds through an own generator (own statics,
quadprog as the controller, the own taut-string cable drag of tests/_cable_drag_truth.py and a
linear zero drift; no wall effects), reduced with the corrections: zero drift, then the cable
windage, modelled or as a measured model-off tare.  Forces within 0.1 N and moments within
0.005 N m per point after the corrections; without each correction the error is larger."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import quadprog
from _cable_drag_truth import string_end_force

from cdpr.analysis.corrections import zero_drift
from cdpr.analysis.dynamics import gravity_wrench
from cdpr.analysis.flow import flow_conditions
from cdpr.analysis.kinematics import structure_matrix
from cdpr.analysis.rigs import paper_rigs
from cdpr.analysis.rotations import rotation_from_euler
from cdpr.analysis.windage import evaluate_windage_tare, fit_windage_tare, windage_of_rig
from cdpr.analysis.wrench import wrench_absolute
from cdpr.pipelines.tunnel_section import tunnel_section_from_mapping

SAMPLE = Path(__file__).resolve().parents[1] / "data_samples" / "tunnel_section_octagon.toml"
SPEEDS = (17.27, 25.51, 41.42)
AOA_DEG = (-6.0, -3.0, 0.0, 3.0, 6.0)
S_REF = 0.0125
S = 1_000_000_000


def _generate(model_on: bool, t0_s: float):
    """Own statics: per point the true tensions for gravity + aero + own cable drag, plus drift."""
    rig = paper_rigs()["flat_optimum"]
    ts = tunnel_section_from_mapping(tomllib.loads(SAMPLE.read_text()), str(SAMPLE))
    g = ts.geometry
    apothem = 0.376 * (1 + 2**0.5) / 2
    yc, zc = np.mean(g.polygon_yz_m, axis=0)
    rho, mu = 1.2041, 1.8134e-5  # 101325 Pa, 293.15 K
    rows = []
    for V in SPEEDS:
        for a_deg in AOA_DEG:
            a = np.deg2rad(a_deg)
            R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
            p = rig.reference_position_O_m
            q = 0.5 * rho * V * V
            W_aero = q * S_REF * np.array([0.05 + 0.4 * a * a, 0, 3.0 * a + 0.1, 0, -0.015 * a, 0])
            if not model_on:
                W_aero = np.zeros(6)
            W_drag = np.zeros(6)
            for i in range(rig.n_cables):
                r = R @ rig.attach_P_m[i]
                F, _ = string_end_force(p + r, rig.anchors_O_m[i], 100.0, V, apothem, yc, zc,
                                        g.x_start_m, g.x_end_m, rho=rho, mu=mu)  # fmt: skip
                W_drag += np.concatenate([F, np.cross(r, F)])
            lv = rig.anchors_O_m - p - rig.attach_P_m @ R.T
            u = lv / np.linalg.norm(lv, axis=1)[:, None]
            A = np.vstack([u.T, np.cross(rig.attach_P_m @ R.T, u).T])
            G = np.concatenate([rig.mass_kg * rig.gravity_O_mps2, np.zeros(3)])
            C = np.hstack([A.T, np.eye(8), -np.eye(8)])
            b = np.concatenate([-(G + W_aero + W_drag), rig.t_min_N, -rig.t_max_N])
            T = quadprog.solve_qp(np.eye(8), np.full(8, 160.0), C, b, meq=6)[0]
            rows.append((V, a, T, W_aero, W_drag))
    n = len(rows)
    t_ns = ((t0_s + 10.0 * (1 + np.arange(n))) * S).astype(np.int64)
    return rig, ts, rows, t_ns


RATE_N_PER_S = np.array([2e-3, -1.5e-3, 1e-3, 0.0, -2e-3, 2.5e-3, 5e-4, -1e-3])


def _reduce(model_on: bool, t0_s: float):
    rig, ts, rows, t_ns = _generate(model_on, t0_s)
    V = np.array([r[0] for r in rows])
    aoa = np.array([r[1] for r in rows])
    T_true = np.array([r[2] for r in rows])
    drift_true = RATE_N_PER_S * (t_ns[:, None] / S)
    T_meas = T_true + drift_true
    # wind-off zeros at the reference pose before and after the run (the same zero load each time)
    zero_t = np.array([0, int(t_ns[-1] + 10 * S)])
    T_zero = np.full((2, 8), 150.0) + RATE_N_PER_S * (zero_t[:, None] / S)
    d = zero_drift(t_ns, zero_t, T_zero, 0.01)
    euler = np.stack([np.zeros_like(aoa), aoa, np.zeros_like(aoa)], axis=1)
    R = rotation_from_euler(euler)
    p = np.broadcast_to(rig.reference_position_O_m, (len(V), 3))
    A = structure_matrix(rig.anchors_O_m, rig.attach_P_m, p, R)
    G = gravity_wrench(rig.mass_kg, rig.com_P_m, R, rig.gravity_O_mps2)
    W_raw = wrench_absolute(A, T_meas, G)
    W_drift = wrench_absolute(A, T_meas - d.drift_N, G)
    fc = flow_conditions(V, 101325.0, 293.15, ts.chord_m, relative_humidity=0.0)
    model = windage_of_rig(
        rig, ts.geometry, p, R, T_meas - d.drift_N, V, fc.density_kgpm3, fc.viscosity_Pas
    )
    W_aero = np.array([r[3] for r in rows])
    return dict(V=V, aoa=aoa, W_raw=W_raw, W_drift=W_drift, model=model, W_aero=W_aero, d=d)


def _errors(W, truth):
    e = W - truth
    return np.abs(e[:, :3]).max(), np.abs(e[:, 3:]).max()


def test_alpha_sweep_within_0p1_N_after_corrections() -> None:
    on = _reduce(True, 100.0)
    truth = on["W_aero"]
    assert not on["d"].no_closing_zero.any()
    # modelled windage
    f_err, m_err = _errors(on["W_drift"] - on["model"].wrench_N, truth)
    assert f_err < 0.1 and m_err < 0.005
    # measured windage tare: model-off points at the same speeds and attitudes, fitted, subtracted
    off = _reduce(False, 2000.0)
    fit = fit_windage_tare(off["V"], off["aoa"], 0.0, off["W_drift"])
    tare = evaluate_windage_tare(fit, on["V"], on["aoa"], 0.0)
    assert not tare.missing.any() and not tare.extrapolated.any()
    f_err_t, m_err_t = _errors(on["W_drift"] - tare.tare_N, truth)
    assert f_err_t < 0.1 and m_err_t < 0.005
    # without each correction the error is out of bounds
    f_no_wind, _ = _errors(on["W_drift"], truth)
    f_no_drift, _ = _errors(on["W_raw"] - on["model"].wrench_N, truth)
    assert f_no_wind > 1.0  # about 1.2 N at 41.42 m/s
    assert f_no_drift > 0.1
