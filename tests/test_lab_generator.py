"""Self-tests of the independent lab generator (tests/lab_generator.py and its _lab_* modules).

Each piece against a source outside the generator: the structure matrix by hand and against
tests/truth_rig.py, the controller against quadprog, Newton-Euler against finite differences of
the linear and angular momentum, the noise processes against their closed forms, the lowest mode
against ``cdpr rig show``, the CAN log against python-can and cantools, the oscillation truth
against the model's derivatives by hand and against the written files, and the files through the
lab path (``cdpr import``, ``cdpr analyze --matrix``, as subprocesses).
"""

from __future__ import annotations

import re
import subprocess
import time
from pathlib import Path

import can
import cantools
import lab_generator as lg
import numpy as np
import pandas as pd
import pytest
import quadprog
import truth_rig
from _lab_aero import AeroModel, Geometry, aero_loads, moist_air_density
from _lab_noise import (
    ar1,
    ar1_long_run_variance,
    ar1_rho,
    ar1_var_of_mean,
    narrowband,
    narrowband_long_run_variance,
    narrowband_rho,
    var_of_mean,
    vector_ar1,
)
from _lab_physics import (
    LabRig,
    Motion,
    body_wrench,
    distribute,
    gravity_wrench,
    modes,
    momenta,
    rate_matrix,
    rot,
    structure_matrix,
)
from measure_coverage import cdpr_command, clean_env

ROOT = Path(__file__).resolve().parents[1]
FLAT = ROOT / "data_samples" / "flat_optimum.toml"
CUBIC = ROOT / "data_samples" / "cubic_optimum.toml"


# ---------------------------------------------------------------------------------------------
# statics


def _toy_rig(anchors: list[list[float]], attach: list[list[float]]) -> LabRig:
    m = len(anchors)
    return LabRig(
        "toy", tuple(f"c{i}" for i in range(m)), np.array(anchors, float), np.array(attach, float),
        np.full(m, 10.0), np.full(m, 100.0), np.full(m, 1e5), 1.0, np.zeros(3), np.eye(3) * 0.01,
        np.array([0.0, 0.0, -9.80665]), np.zeros(6),
    )  # fmt: skip


def test_structure_matrix_by_hand() -> None:
    rig = _toy_rig([[1.0, 0.0, 0.0], [0.0, 0.0, 2.0]], [[0.0, 0.1, 0.0], [0.1, 0.0, 0.0]])
    # level at the origin: cable 0 runs along (1, -0.1, 0); its moment arm (0, 0.1, 0)
    A = structure_matrix(rig, np.zeros((1, 6)))[0]
    s = np.sqrt(1.01)
    np.testing.assert_allclose(A[:, 0], [1 / s, -0.1 / s, 0, 0, 0, -0.1 / s], atol=1e-15)
    # cable 1: from (0.1, 0, 0) to (0, 0, 2): u = (-0.1, 0, 2)/|.|, r x u = (0, -0.2, 0)/|.|
    s1 = np.sqrt(4.01)
    np.testing.assert_allclose(A[:, 1], [-0.1 / s1, 0, 2 / s1, 0, -0.2 / s1, 0], atol=1e-15)
    # yaw 90 deg turns pp0 to (-0.1, 0, 0): the cable runs along +x through P, no moment
    A = structure_matrix(rig, np.array([[0, 0, 0, 0, 0, np.pi / 2]]))[0]
    np.testing.assert_allclose(A[:, 0], [1, 0, 0, 0, 0, 0], atol=1e-15)
    # pitch 90 deg (about y) turns pp1 = (0.1, 0, 0) to (0, 0, -0.1): cable straight up, no moment
    A = structure_matrix(rig, np.array([[0, 0, 0, 0, np.pi / 2, 0]]))[0]
    np.testing.assert_allclose(A[:, 1], [0, 0, 1, 0, 0, 0], atol=1e-15)


@pytest.mark.parametrize("path", [FLAT, CUBIC], ids=["flat", "cubic"])
def test_structure_matrix_and_gravity_against_truth_rig(path: Path) -> None:
    rig = LabRig.from_toml(path)
    rng = np.random.default_rng(1)
    q = rig.reference_pose + np.concatenate(
        [rng.uniform(-0.02, 0.02, (20, 3)), np.deg2rad(rng.uniform(-8, 8, (20, 3)))], axis=1
    )
    A = structure_matrix(rig, q)
    G = gravity_wrench(rig.with_body(com_P_m=np.array([0.01, -0.02, 0.005])), q)
    for k in range(len(q)):
        np.testing.assert_allclose(
            A[k], truth_rig.statics(rig.anchors_O_m, rig.attach_P_m, q[k]), atol=1e-13
        )
        np.testing.assert_allclose(
            G[k], truth_rig.weight(rig.mass_kg, np.array([0.01, -0.02, 0.005]), q[k]), atol=1e-12
        )


# ---------------------------------------------------------------------------------------------
# the controller


def _quadprog(A: np.ndarray, w: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    m = A.shape[1]
    C = np.hstack([A.T, np.eye(m), -np.eye(m)])
    b = np.concatenate([w, lo, -hi])
    return np.asarray(quadprog.solve_qp(np.eye(m), 0.5 * (lo + hi), C, b, meq=6)[0])


@pytest.mark.parametrize("path", [FLAT, CUBIC], ids=["flat", "cubic"])
def test_tension_distribution_against_quadprog(path: Path) -> None:
    rig = LabRig.from_toml(path)
    rng = np.random.default_rng(2)
    n = 80
    cubic = path == CUBIC
    # the flat rig holds little yaw (a cable slackens past ~0.7 deg) and little roll moment
    ang = np.array([4.0, 4.0, 4.0]) if cubic else np.array([1.0, 5.0, 0.3])
    q = rig.reference_pose + np.concatenate(
        [rng.uniform(-0.01, 0.01, (n, 3)), np.deg2rad(rng.uniform(-ang, ang, (n, 3)))], axis=1
    )
    A = structure_matrix(rig, q)
    # aero-sized loads; per-cable limits that differ: the rig's, narrowed by a little in the first
    # half, narrow bands (that bring cables to a limit: the QP path) in the second
    Wmax = np.array([60, 60, 60, 4, 4, 4]) if cubic else np.array([8, 3, 8, 0.01, 0.05, 0.005])
    W = rng.uniform(-1, 1, (n, 6)) * Wmax
    w = -gravity_wrench(rig, q) - W
    lo = rig.t_min_N + rng.uniform(0, 10, (n, rig.m))
    hi = rig.t_max_N - rng.uniform(0, 30, (n, rig.m))
    a, b, c, d = (250, 400, 150, 350) if cubic else (80, 120, 70, 110)
    lo[n // 2 :] = rng.uniform(a, b, (n - n // 2, rig.m))
    hi[n // 2 :] = lo[n // 2 :] + rng.uniform(c, d, (n - n // 2, rig.m))
    feasible, T_ref = [], []
    for k in range(n):
        try:
            T_ref.append(_quadprog(A[k], w[k], lo[k], hi[k]))
            feasible.append(k)
        except ValueError:  # inconsistent constraints: not a case for the comparison
            pass
    idx = np.array(feasible)
    T = np.empty((len(idx), rig.m))
    n_qp = 0
    for j, k in enumerate(idx):  # per-case limits
        T[j], used = distribute(A[k : k + 1], w[k : k + 1], lo[k], hi[k])
        n_qp += used
    assert len(idx) >= 0.6 * n
    assert n_qp >= 5, "too few cases reached a limit: the QP path is untested"
    np.testing.assert_allclose(T, np.array(T_ref), atol=1e-6)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", A[idx], T), w[idx], atol=1e-7)


# ---------------------------------------------------------------------------------------------
# dynamics


def _body() -> LabRig:
    rig = LabRig.from_toml(FLAT)
    I = np.array([[0.0012, 2e-4, -1e-4], [2e-4, 0.008, 3e-4], [-1e-4, 3e-4, 0.0075]])
    return rig.with_body(0.7, np.array([0.004, -0.003, 0.006]), I)


def _trajectory(t: np.ndarray):
    """A smooth motion on all six coordinates at once (analytic q, qd, qdd)."""
    q0 = np.array([0.5, 0.01, 0.33, 0.05, 0.1, -0.04])
    a = np.array([0.01, 0.02, 0.015, 0.2, 0.15, 0.25])
    w = np.array([3.1, 4.7, 2.3, 5.9, 3.7, 6.3])
    ph = np.array([0.1, 1.2, 2.0, 0.4, 2.9, 1.7])
    x = w * t[:, None] + ph
    return q0 + a * np.sin(x), a * w * np.cos(x), -a * w * w * np.sin(x)


def test_newton_euler_against_momentum_derivatives() -> None:
    """F = dL/dt and M_P = dH_O/dt - p x F (H_O about the fixed origin of {O})."""
    rig = _body()
    t = np.linspace(0.0, 2.0, 41)
    h = 1e-5
    q, qd, qdd = _trajectory(t)
    D = body_wrench(rig, q, qd, qdd)
    Lp, Hp = momenta(rig, *_trajectory(t + h)[:2])
    Lm, Hm = momenta(rig, *_trajectory(t - h)[:2])
    F = (Lp - Lm) / (2 * h)
    M_O = (Hp - Hm) / (2 * h)
    np.testing.assert_allclose(D[:, :3], F, rtol=0, atol=1e-7 * np.abs(F).max())
    M_P = M_O - np.cross(q[:, :3], F)
    np.testing.assert_allclose(D[:, 3:], M_P, rtol=0, atol=1e-6 * np.abs(M_P).max())
    assert np.abs(D[:, 3:]).max() > 1e-3  # the rotational terms are exercised


def test_euler_rate_matrix_against_rotation_derivative() -> None:
    t = np.linspace(0.0, 1.0, 11)
    h = 1e-6
    q, qd, _ = _trajectory(t)
    Rd = (rot(_trajectory(t + h)[0][:, 3:]) - rot(_trajectory(t - h)[0][:, 3:])) / (2 * h)
    W = Rd @ np.swapaxes(rot(q[:, 3:]), 1, 2)  # [omega]x
    omega = np.stack([W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]], axis=1)
    np.testing.assert_allclose(
        np.einsum("nij,nj->ni", rate_matrix(q[:, 3:]), qd[:, 3:]), omega, atol=1e-8
    )


def test_motion_follows_the_spec_and_its_derivatives() -> None:
    mo = Motion("pitch", np.deg2rad(5.0), 2.0, 4, 2, (0.5, 0, 0.335, 0, 0.05, 0), t0_s=1.0)
    assert mo.window_s == pytest.approx((2.0, 4.0))
    assert mo.stop_s == pytest.approx(4.5)
    t = np.linspace(0.5, 5.0, 901)
    q, qd, qdd = mo.states(t)
    h = 1e-6
    qp, qdp, _ = mo.states(t + h)
    qm, qdm, _ = mo.states(t - h)
    inside = np.all(np.abs(t[:, None] - np.array([1.0, 2.0, 4.0, 4.5])) > 2 * h, axis=1)
    np.testing.assert_allclose(((qp - qm) / (2 * h))[inside], qd[inside], atol=1e-7)
    np.testing.assert_allclose(((qdp - qdm) / (2 * h))[inside], qdd[inside], atol=1e-5)
    # before t0 and after the ramp-down: the mean pose; in the window: A sin(w (t - t0))
    np.testing.assert_allclose(
        q[(t < 1.0) | (t > 4.5)], np.tile(mo.q_mean, (np.sum((t < 1.0) | (t > 4.5)), 1)), atol=1e-15
    )
    w = (t >= 2.0) & (t <= 4.0)
    np.testing.assert_allclose(
        q[w, 4], 0.05 + np.deg2rad(5.0) * np.sin(4 * np.pi * (t[w] - 1.0)), atol=1e-14
    )
    # the envelope: raised cosine up over the settling cycles
    e, _, _ = mo.envelope(np.array([1.0, 1.5, 2.0, 4.25, 4.5]))
    np.testing.assert_allclose(e, [0.0, 0.5, 1.0, 0.5, 0.0], atol=1e-12)


# ---------------------------------------------------------------------------------------------
# noise closed forms


def test_ar1_autocorrelation_and_long_run_variance() -> None:
    rng = np.random.default_rng(3)
    dt, tau, sd = 1e-3, 0.03, 0.05
    n, batch = 2_000_000, 2000
    x = ar1(rng, n, np.array([sd]), np.array([tau]), dt)[:, 0]
    rho = float(ar1_rho(tau, dt))
    assert np.var(x) == pytest.approx(sd**2, rel=0.05)
    for lag in (1, 10, 30, 60):
        r = np.mean(x[:-lag] * x[lag:]) / np.var(x)
        assert r == pytest.approx(rho**lag, abs=0.02)
    means = x.reshape(-1, batch).mean(axis=1)  # 1000 batch means
    exact = ar1_var_of_mean(sd, rho, batch)
    assert np.var(means) == pytest.approx(exact, rel=0.15)  # sd of the estimate: 4.5 %
    # the closed form of the long-run variance is the large-window limit of the exact one
    assert ar1_long_run_variance(sd, rho) / batch == pytest.approx(exact, rel=0.02)
    # and what sd/sqrt(n) misses at 1 kHz with tau = 30 ms: about 7.7
    assert np.sqrt(ar1_long_run_variance(sd, rho)) / sd == pytest.approx(7.7, rel=0.01)


def test_vector_ar1_covariance_and_long_run_covariance() -> None:
    rng = np.random.default_rng(4)
    S = lg.LoadCellNoise(case="common").common_cov()
    dt, tau, batch = 1e-3, 0.03, 2000
    x = vector_ar1(rng, 2_000_000, S, tau, dt)
    sd = np.sqrt(np.diag(S))
    np.testing.assert_allclose(np.cov(x.T) / np.outer(sd, sd), S / np.outer(sd, sd), atol=0.03)
    rho = float(ar1_rho(tau, dt))
    means = x.reshape(-1, batch, 6).mean(axis=1)
    want = S * (1 + rho) / (1 - rho) / batch
    got = np.cov(means.T)
    np.testing.assert_allclose(np.diag(got) / np.diag(want), 1.0, atol=0.2)
    np.testing.assert_allclose(got[2, 4] / np.sqrt(got[2, 2] * got[4, 4]), -0.8, atol=0.05)


def test_narrowband_autocorrelation_and_long_run_variance() -> None:
    rng = np.random.default_rng(5)
    dt, f0, Q = 1e-3, 9.2, 30.0
    x = narrowband(rng, 2_000_000, f0, Q, dt, sd=0.3)
    rho, theta = narrowband_rho(f0, Q, dt), 2 * np.pi * f0 * dt
    assert np.var(x) == pytest.approx(0.09, rel=0.1)
    for lag in (1, 27, 54, 109, 300):
        r = np.mean(x[:-lag] * x[lag:]) / np.var(x)
        assert r == pytest.approx(rho**lag * np.cos(theta * lag), abs=0.05)
    spec = np.abs(np.fft.rfft(x[:200_000])) ** 2
    f = np.fft.rfftfreq(200_000, dt)
    assert abs(f[np.argmax(spec)] - f0) < 0.5
    # the variance of a 2 s window's mean from the autocovariance, and its long-run limit
    h = np.arange(2_000_000)
    acov = 0.09 * rho**h * np.cos(theta * h)
    means = x.reshape(-1, 2000).mean(axis=1)
    assert np.var(means) == pytest.approx(var_of_mean(acov, 2000), rel=0.15)
    assert 2_000_000 * var_of_mean(acov, 2_000_000) == pytest.approx(
        narrowband_long_run_variance(0.3, rho, theta), rel=0.01
    )


# ---------------------------------------------------------------------------------------------
# aero model


def test_aero_model_signs_and_axes_by_hand() -> None:
    model, geom = AeroModel(), Geometry(mrp_P_m=(0.0, 0.0, 0.0))
    assert float(moist_air_density(101325.0, 288.15, 0.0)) == pytest.approx(1.2250, abs=1e-4)
    q = np.array([[0.5, 0, 0.3, 0, 0, 0]])
    ld = aero_loads(model, geom, q, None, None, np.array([30.0]), 1.2)
    qS = 0.5 * 1.2 * 900 * geom.area_m2
    CL, CD, Cm = model.CL0, model.CD0 + model.CDk * model.CL0**2, model.Cm0
    # level, nose upstream: drag along +x_O, lift along +z_O, a nose-up moment about +y_O
    np.testing.assert_allclose(
        ld.wrench_P_O[0], [CD * qS, 0, CL * qS, 0, Cm * qS * geom.chord_m, 0], atol=1e-12
    )
    # pitch = aoa, yaw = sideslip (nose upstream), roll neither
    for pose, aoa, beta in (([0, 0.1, 0], 0.1, 0), ([0, 0, 0.05], 0, 0.05), ([0.2, 0, 0], 0, 0)):
        ld = aero_loads(
            model, geom, np.array([[0.5, 0, 0.3, *pose]]), None, None, np.array([30.0]), 1.2
        )
        assert ld.aoa_rad[0] == pytest.approx(aoa, abs=1e-12)
        assert ld.sideslip_rad[0] == pytest.approx(beta, abs=1e-12)
    # positive sideslip: side force along -y_B = -y_O (CYb < 0 pushes to the left wing), and at aoa
    # lift stays normal to the stream (+z_O) and drag along it (+x_O)
    ld = aero_loads(
        model, geom, np.array([[0.5, 0, 0.3, 0, 0.1, 0]]), None, None, np.array([30.0]), 1.2
    )
    CL = model.CL0 + model.CLa * 0.1
    CD = model.CD0 + model.CDk * CL**2
    np.testing.assert_allclose(ld.wrench_P_O[0, :3], [CD * qS, 0, CL * qS], atol=1e-12)
    # a moment reference point ahead of P (the nose side, -x_P): M_P = M_mrp + r x F
    g2 = Geometry(mrp_P_m=(-0.05, 0.0, 0.0))
    ld2 = aero_loads(model, g2, q, None, None, np.array([30.0]), 1.2)
    F = ld2.wrench_P_O[0, :3]
    np.testing.assert_allclose(
        ld2.wrench_P_O[0, 3:], ld2.wrench_mrp_O[0, 3:] + np.cross([-0.05, 0, 0], F), atol=1e-14
    )


def test_pitching_rate_gives_the_damping_derivatives() -> None:
    """A pure pitch rate about P (MRP at P): Cm gains (Cmq + Cmadot) q c/2V, CL (CLq + CLadot)."""
    model, geom = AeroModel(), Geometry()
    V, qrate = 30.0, 0.7
    q = np.array([[0.5, 0, 0.3, 0, 0.0, 0]])
    qd = np.array([[0, 0, 0, 0, qrate, 0]])
    ld = aero_loads(model, geom, q, qd, np.zeros((1, 6)), np.array([V]), 1.2)
    qhat = qrate * geom.chord_m / (2 * V)
    assert ld.rates_B[0, 1] == pytest.approx(qrate)
    assert ld.coefficients[0, 4] == pytest.approx(
        model.Cm0 + (model.Cmq + model.Cmadot) * qhat, rel=1e-9
    )
    assert ld.coefficients[0, 2] == pytest.approx(
        model.CL0 + (model.CLq + model.CLadot) * qhat, rel=1e-9
    )
    # yaw rate: body r = -yaw_dot (nose upstream), sideslip_dot = +yaw_dot
    qd = np.array([[0, 0, 0, 0, 0, qrate]])
    ld = aero_loads(model, geom, q, qd, np.zeros((1, 6)), np.array([V]), 1.2)
    bh = qrate * geom.span_m / (2 * V)
    assert ld.rates_B[0, 2] == pytest.approx(-qrate)
    assert ld.coefficients[0, 5] == pytest.approx(-model.Cnr * bh + model.Cnbdot * bh, rel=1e-9)


# ---------------------------------------------------------------------------------------------
# the lowest mode against cdpr rig show


@pytest.mark.parametrize("path", [FLAT, CUBIC], ids=["flat", "cubic"])
def test_modes_against_cdpr_rig_show(path: Path) -> None:
    """Six natural frequencies within 1 % of `cdpr rig show` (its numbers have 2 decimals; the
    flat optimum's lowest is about 9.2 Hz)."""
    argv = [*cdpr_command(), "rig", "show", str(path)]
    r = subprocess.run(argv, capture_output=True, text=True, env=clean_env(), check=True)
    shown = np.array([float(x) for x in re.findall(r"mode \d:\s+([\d.]+) Hz", r.stdout)])
    assert len(shown) == 6, r.stdout
    rig = LabRig.from_toml(path)
    q = rig.reference_pose
    T, _ = distribute(
        structure_matrix(rig, q[None]), -gravity_wrench(rig, q[None]), rig.t_min_N, rig.t_max_N
    )
    f, _ = modes(rig, q, T[0])
    np.testing.assert_allclose(f, shown, rtol=0.01)
    if path == FLAT:
        assert 9.0 < f[0] < 9.5 and 120 < f[-1] < 125


# ---------------------------------------------------------------------------------------------
# the files


@pytest.fixture(scope="module")
def small_case(tmp_path_factory: pytest.TempPathFactory) -> lg.LabCase:
    """One block: zero, tares at 0 and 4 deg, wind-on at 25.51 m/s, closing zero; 1.5 s points."""
    out = tmp_path_factory.mktemp("lab") / "case"
    return lg.steady_case(
        out, "ar1", 2, duration_s=1.5, seed=7,
        plan_kw={"aoa_deg": (0.0, 4.0), "speeds_mps": (25.51,)},
    )  # fmt: skip


def test_can_log_decodes_with_python_can_and_cantools(small_case: lg.LabCase) -> None:
    f = small_case.files
    t_ns, counts = lg.read_candump(f["can_log"])
    db = cantools.database.load_file(str(f["dbc"]))
    msgs = []
    with can.LogReader(str(f["can_log"])) as reader:
        for k, msg in enumerate(reader):
            msgs.append(msg)
            if k >= 4 * 300 - 1:
                break
    for k, msg in enumerate(msgs):
        s, fi = divmod(k, 4)
        assert msg.arbitration_id == lg.FRAME_IDS[fi]
        # python-can's float seconds: to within its resolution (~0.1 us at 1.7e9 s)
        assert abs(msg.timestamp * 1e9 - (t_ns[s] + fi * lg.FRAME_SPACING_NS)) < 1000
        sig = db.decode_message(msg.arbitration_id, msg.data, decode_choices=False)
        assert sig[f"Ch{2 * fi + 1}_Counts"] == counts[s, 2 * fi]
        assert sig[f"Ch{2 * fi + 2}_Counts"] == counts[s, 2 * fi + 1]
        assert sig["Counter"] == s % 256
        assert sig[f"Ch{2 * fi + 1}_Slack"] == 0
    assert np.all(np.diff(t_ns) == 1_000_000)


def test_counts_and_calibration_give_the_tensions_of_the_truth(small_case: lg.LabCase) -> None:
    """Per point and cable, the decoded window mean equals the truth's noise-free tension plus
    the realised drift, white and AR(1) means (to the calibration's own error)."""
    f, truth = small_case.files, small_case.truth
    import tomllib

    cal = tomllib.loads(f["calibration"].read_text())["calibration"]
    t_ns, counts = lg.read_candump(f["can_log"])
    T = (counts - np.array(cal["offset_counts"])) * np.array(cal["gain_N_per_count"])
    for p in truth["points"]:
        sel = (t_ns >= p["start_ns"]) & (t_ns <= p["end_ns"])
        assert sel.sum() == p["n_samples"]
        want = (
            np.array(p["tension_true_mean_N"])
            + np.array(p["drift_mean_N"])
            + np.array(p["white_mean_N"])
            + np.array(p["ar1_mean_N"])
        )
        np.testing.assert_allclose(T[sel].mean(axis=0), want, atol=2e-3)
    assert cal["cables"] == truth["rig_cables"]


def test_generator_is_deterministic_by_seed(tmp_path: Path) -> None:
    kw = {"duration_s": 0.5, "plan_kw": {"aoa_deg": (0.0,), "speeds_mps": (25.51,)}}
    a = lg.steady_case(tmp_path / "a", "common", 1, seed=3, **kw)
    b = lg.steady_case(tmp_path / "b", "common", 1, seed=3, **kw)
    c = lg.steady_case(tmp_path / "c", "common", 1, seed=4, **kw)
    for k in ("can_log", "poses", "tunnel", "events", "calibration"):
        assert a.files[k].read_bytes() == b.files[k].read_bytes()
    assert a.files["can_log"].read_bytes() != c.files["can_log"].read_bytes()


def test_camera_clock_offset_and_covariance(small_case: lg.LabCase) -> None:
    """A frame stamped t_cam shows the pose at t_cam - offset; its covariance is symmetric,
    positive and (Euler parametrisation) the camera's rotation-vector noise through H^-1."""
    df = pd.read_csv(small_case.files["poses"])
    truth = small_case.truth
    off = truth["camera"]["camera_clock_offset_ns"]
    assert off == 3_000_000
    assert np.all(np.diff(df["t_ns"]) == 10_000_000)
    C = df[list(lg.COV_COLUMNS)].to_numpy().reshape(-1, 6, 6)
    assert np.array_equal(C, np.swapaxes(C, 1, 2))
    assert np.all(np.linalg.eigvalsh(C) > 0)
    sd_pos = np.sqrt(C[:, 0, 0])
    assert 0.8 * 0.05e-3 <= sd_pos.min() and sd_pos.max() <= 1.2 * 0.05e-3 + 1e-12
    # the 4 deg tare: pitch frames inside its window scatter about the true pitch by their sd
    p = next(p for p in truth["points"] if p["point"] == "tare1-a4-b0")
    sel = (df["t_ns"] - off >= p["start_ns"]) & (df["t_ns"] - off <= p["end_ns"])
    z = (df.loc[sel, "pitch_rad"] - p["true_pitch_rad"]) / np.sqrt(C[sel.to_numpy(), 4, 4])
    assert abs(z.mean()) < 4 / np.sqrt(sel.sum()) and 0.7 < z.std() < 1.3


# ---------------------------------------------------------------------------------------------
# the lab path


def test_files_import_and_analyse_with_cdpr(small_case: lg.LabCase, tmp_path: Path) -> None:
    """`cdpr import` takes the files, `cdpr analyze --matrix` reduces them (subprocesses); every
    point comes back with its label and kind, the wrench near the truth (the flat rig's tare
    method: forces within 0.03 N, moments within 3 mN m)."""
    run, ana = tmp_path / "run.mcap", tmp_path / "analysis"
    imp, an = lg.lab_argv(small_case, run, ana)
    t0 = time.monotonic()
    r = subprocess.run(cdpr_command() + imp, capture_output=True, text=True, env=clean_env())
    assert r.returncode == 0, r.stderr
    r = subprocess.run(cdpr_command() + an, capture_output=True, text=True, env=clean_env())
    assert r.returncode in (0, 1), r.stderr  # 1: warnings (no windage, nominal pose sd today)
    assert time.monotonic() - t0 < 120
    pts = pd.read_csv(ana / "run" / "points.csv")
    truth = small_case.points
    assert list(pts["point"]) == list(truth["point"])
    assert list(pts["kind"]) == list(truth["kind"])
    m = pts.merge(truth, on="point", suffixes=("", "_true"))
    on = m[m["kind"] == "wind_on"]
    assert len(on) == 2
    np.testing.assert_allclose(on["airspeed_mps"], on["airspeed_mps_true"], atol=0.05)
    np.testing.assert_allclose(
        on[["fx_N", "fy_N", "fz_N"]].to_numpy(),
        on[["fx_N_true", "fy_N_true", "fz_N_true"]].to_numpy(),
        atol=0.03,
    )
    np.testing.assert_allclose(
        on[["mx_Nm", "my_Nm", "mz_Nm"]].to_numpy(),
        on[["mx_Nm_true", "my_Nm_true", "mz_Nm_true"]].to_numpy(),
        atol=3e-3,
    )
    np.testing.assert_allclose(on["CL"], on["CL_true"], atol=0.01)
    assert (on["tare_point"] == ["tare1-a0-b0", "tare1-a4-b0"]).all()


# ---------------------------------------------------------------------------------------------
# oscillation points


@pytest.fixture(scope="module")
def osc_case(tmp_path_factory: pytest.TempPathFactory) -> lg.LabCase:
    out = tmp_path_factory.mktemp("osc") / "case"
    specs = (
        lg.OscSpec("pitch", 5.0, 2.0, (41.42,), 10),
        lg.OscSpec("yaw", 0.5, 1.0, (25.51,), 4, aoa_deg=4.0),
    )
    return lg.oscillation_case(out, specs, seed=11)


def test_oscillation_truth_is_the_models_derivatives(osc_case: lg.LabCase) -> None:
    m = AeroModel()
    pts = {p["point"]: p for p in osc_case.truth["points"]}
    o = pts["osc-pitch-A5d-f2-a0-v41.42"]["oscillation"]
    assert o["named"]["Cma"] == pytest.approx(m.Cma, rel=1e-6)
    assert o["named"]["Cmq_plus_Cmadot"] == pytest.approx(m.Cmq + m.Cmadot, rel=1e-6)
    assert o["named"]["CLa"] == pytest.approx(m.CLa, rel=1e-6)
    assert o["named"]["CLq_plus_CLadot"] == pytest.approx(m.CLq + m.CLadot, rel=1e-5)
    assert o["reduced_frequency"] == pytest.approx(4 * np.pi * 0.06 / (2 * 41.42))
    y = pts["osc-yaw-A0.5d-f1-a4-v25.51"]["oscillation"]
    a = np.deg2rad(4.0)
    assert y["inphase"]["Cn"] == pytest.approx(m.Cnb, rel=1e-4)
    assert y["outphase"]["Cn"] == pytest.approx(
        -m.Cnr * np.cos(a) + m.Cnp * np.sin(a) + m.Cnbdot, rel=1e-4
    )
    assert y["outphase"]["Cl"] == pytest.approx(m.Clp * np.sin(a) - m.Clr * np.cos(a), rel=1e-4)
    tare = pts["osc-tare-pitch-A5d-f2-a0"]["oscillation"]
    assert "inphase" not in tare and len(tare["inertia_gravity_harmonics_P_O"]) == 6


def test_oscillation_files_give_back_the_truth(osc_case: lg.LabCase) -> None:
    """A minimal reduction of the written files (not cdpr's): the decoded tensions, the known
    motion at the load-cell times, the wind-off tare's cable wrench subtracted sample by sample,
    Cm in body axes fitted by harmonics: in-phase within 1 %, out-of-phase within 3 %.  The
    camera's pitch, fitted the same way, lags the motion by the clock offset."""
    import tomllib

    f, truth = osc_case.files, osc_case.truth
    cal = tomllib.loads(f["calibration"].read_text())["calibration"]
    t_ns, counts = lg.read_candump(f["can_log"])
    T = (counts - np.array(cal["offset_counts"])) * np.array(cal["gain_N_per_count"])
    rig = LabRig.from_toml(f["rig"])
    pts = {p["point"]: p for p in truth["points"]}
    on, tare = pts["osc-pitch-A5d-f2-a0-v41.42"], pts["osc-tare-pitch-A5d-f2-a0"]

    def window(p):
        o = p["oscillation"]
        sel = (t_ns >= o["window_ns"][0]) & (t_ns <= o["window_ns"][1])
        tau = (t_ns[sel] - o["t0_ns"]) * 1e-9
        mo = Motion(
            o["axis"],
            o["amplitude"],
            o["frequency_Hz"],
            o["cycles"],
            o["settling_cycles"],
            tuple(o["q_mean"]),
            0.0,
        )
        q = mo.states(tau)[0]
        A = structure_matrix(rig, q)
        return tau, q, np.einsum("nij,nj->ni", A, T[sel])

    tau, q, w_on = window(on)
    tau2, _, w_tare = window(tare)
    assert len(tau) == len(tau2) and np.allclose(tau, tau2)
    W = -(w_on - w_tare)  # the aerodynamic load at P in {O}
    R_O_B = rot(q[:, 3:]) @ np.diag([-1.0, 1.0, -1.0])
    M_B = np.einsum("nji,nj->ni", R_O_B, W[:, 3:])
    qSc = on["q_Pa"] * 0.014646 * 0.060
    w = 2 * np.pi * 2.0
    X = np.column_stack([np.ones_like(tau), np.sin(w * tau), np.cos(w * tau)])
    c0, a1, b1 = np.linalg.lstsq(X, M_B[:, 1] / qSc, rcond=None)[0]
    o = on["oscillation"]
    assert a1 / o["amplitude"] == pytest.approx(o["named"]["Cma"], rel=0.01)
    assert b1 / (o["amplitude"] * o["reduced_frequency"]) == pytest.approx(
        o["named"]["Cmq_plus_Cmadot"], rel=0.03
    )
    # the camera: frames stamped t_cam show the motion at t_cam - offset
    df = pd.read_csv(f["poses"])
    tc = (df["t_ns"].to_numpy() - o["t0_ns"]) * 1e-9
    sel = (tc > (o["window_ns"][0] - o["t0_ns"]) * 1e-9 + 0.01) & (
        tc < (o["window_ns"][1] - o["t0_ns"]) * 1e-9 - 0.01
    )
    X = np.column_stack([np.ones(sel.sum()), np.sin(w * tc[sel]), np.cos(w * tc[sel])])
    _, s1, k1 = np.linalg.lstsq(X, df["pitch_rad"].to_numpy()[sel], rcond=None)[0]
    lag_s = np.arctan2(-k1, s1) / w
    assert lag_s == pytest.approx(truth["camera"]["camera_clock_offset_ns"] * 1e-9, abs=2e-5)


def test_oscillation_files_import_and_analyse_with_cdpr(
    osc_case: lg.LabCase, tmp_path: Path
) -> None:
    run, ana = tmp_path / "run.mcap", tmp_path / "analysis"
    imp, an = lg.lab_argv(osc_case, run, ana)
    r = subprocess.run(cdpr_command() + imp, capture_output=True, text=True, env=clean_env())
    assert r.returncode == 0, r.stderr
    r = subprocess.run(cdpr_command() + an, capture_output=True, text=True, env=clean_env())
    assert r.returncode in (0, 1), r.stderr
    pts = pd.read_csv(ana / "run" / "points.csv")
    assert set(osc_case.points["point"]) <= set(pts["point"])


def test_common_mode_and_ringing_mode_in_the_files(tmp_path: Path) -> None:
    """The fluctuating aerodynamic load reaches the files as the cables' wrench (its Fz scatter is
    q S sd(CL) beside the cells' white noise); the ringing mode shows in the tensions' spectrum
    at the lowest natural frequency."""
    import tomllib

    kw = {"duration_s": 3.0, "plan_kw": {"aoa_deg": (0.0,), "speeds_mps": (41.42,)}}
    for case in ("common", "mode"):
        c = lg.steady_case(tmp_path / case, case, 1, seed=5, **kw)
        cal = tomllib.loads(c.files["calibration"].read_text())["calibration"]
        t_ns, counts = lg.read_candump(c.files["can_log"])
        T = (counts - np.array(cal["offset_counts"])) * np.array(cal["gain_N_per_count"])
        p = next(p for p in c.truth["points"] if p["kind"] == "wind_on")
        sel = (t_ns >= p["start_ns"]) & (t_ns <= p["end_ns"])
        if case == "common":
            rig = LabRig.from_toml(c.files["rig"])
            q = np.array([p[f"true_{k}"] for k in lg.POSE_COLUMNS])
            A = structure_matrix(rig, q[None])[0]
            fz = -(T[sel] @ A[2])
            white = 0.05**2 * np.sum(A[2] ** 2)
            qS = p["q_Pa"] * Geometry().area_m2
            want = white + (qS * lg.LoadCellNoise().common_sd[2]) ** 2
            assert np.var(fz) == pytest.approx(want, rel=0.3)
            assert np.var(fz) > 2 * white
        else:
            f0 = c.truth["lowest_mode"]["frequency_Hz"]
            k = int(np.argmax(c.truth["lowest_mode"]["tension_rms_per_unit_N"]))
            x = T[sel, k] - T[sel, k].mean()
            spec = np.abs(np.fft.rfft(x * np.hanning(len(x)))) ** 2
            f = np.fft.rfftfreq(len(x), 1e-3)
            band = (f > 3) & (f < 60)
            assert abs(f[band][np.argmax(spec[band])] - f0) < 0.5
            assert 8.5 < f0 < 9.5


def test_cdpr_dynamic_correction_removes_the_inertia_of_a_wind_off_oscillation(
    osc_case: lg.LabCase,
) -> None:
    """cdpr's absolute method with its model inertia (``recover_wrench(...,
    inertia_wrench_N=inertia_wrench_from_poses(...))``, the rig file given the generator's true
    body) on the wind-off pitch oscillation of the files: the pitching moment's first harmonic
    must vanish (the model's inertia is ~0.11 N m at 5 deg and 2 Hz); the truth here is the
    generator's Newton-Euler, checked against the momentum's derivatives above."""
    import dataclasses
    import tomllib

    from cdpr.analysis.wrench import inertia_wrench_from_poses, recover_wrench
    from cdpr.pipelines.config import load_rig

    f, truth = osc_case.files, osc_case.truth
    cal = tomllib.loads(f["calibration"].read_text())["calibration"]
    t_ns, counts = lg.read_candump(f["can_log"])
    T = (counts - np.array(cal["offset_counts"])) * np.array(cal["gain_N_per_count"])
    o = next(p for p in truth["points"] if p["point"] == "osc-tare-pitch-A5d-f2-a0")["oscillation"]
    sel = (t_ns >= o["window_ns"][0]) & (t_ns <= o["window_ns"][1])
    tau = (t_ns[sel] - o["t0_ns"]) * 1e-9
    mo = Motion("pitch", o["amplitude"], o["frequency_Hz"], o["cycles"], o["settling_cycles"],
                tuple(o["q_mean"]), 0.0)  # fmt: skip
    q = mo.states(tau)[0]
    b = truth["body_true"]
    rig = dataclasses.replace(
        load_rig(f["rig"]), mass_kg=b["mass_kg"], com_P_m=np.array(b["com_P_m"]),
        inertia_P_kgm2=np.array(b["inertia_P_kgm2"]),
    )  # fmt: skip
    D = inertia_wrench_from_poses(rig.mass_kg, rig.com_P_m, rig.inertia_P_kgm2, q, t_ns[sel])
    W = recover_wrench(rig, q, T[sel], inertia_wrench_N=D)
    w = 2 * np.pi * o["frequency_Hz"]
    X = np.column_stack([np.ones_like(tau), np.sin(w * tau), np.cos(w * tau)])
    amp_D = np.hypot(*np.linalg.lstsq(X, D[:, 4], rcond=None)[0][1:])
    amp_W = np.hypot(*np.linalg.lstsq(X, W[:, 4], rcond=None)[0][1:])
    assert amp_D > 0.05
    assert amp_W < 0.05 * amp_D
