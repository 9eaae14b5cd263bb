"""Force sensitivity (paper eq. 12): batched geometry and S against independent references.

References: the Rig builders + kinematics (a separate code path from the vectorised geometry),
numpy's pseudo-inverse, quadprog's QP solver and the foundation's wrench covariance.
"""

from __future__ import annotations

import numpy as np
import pytest
import quadprog

from cdpr.analysis import rigs
from cdpr.analysis import sensitivity as sens
from cdpr.analysis.errors import InputError
from cdpr.analysis.kinematics import structure_matrix
from cdpr.analysis.uncertainty import wrench_covariance

RNG = np.random.default_rng(20240607)


def _A_of(rig) -> np.ndarray:
    return structure_matrix(rig.anchors_O_m, rig.attach_P_m, rig.reference_position_O_m, np.eye(3))


@pytest.mark.parametrize("layout", ["crossed", "cube"])
def test_cubic_geometry_matches_rig_builder(layout: str) -> None:
    k = np.sort(RNG.uniform(0.025, 0.4, size=(20, 3)), axis=1)[:, ::-1]  # k1 >= k2 >= k3
    Z = RNG.uniform(0.4, 1.0, size=20)
    A = sens.structure_matrices(
        sens.cubic_geometry(k[:, 0], k[:, 1], k[:, 2], Z_m=Z, layout=layout)
    )
    assert A.shape == (20, 6, 8)
    for i in range(20):
        rig = rigs.cubic_rig(*k[i], Z_m=Z[i], layout=layout)
        np.testing.assert_allclose(A[i], _A_of(rig), atol=1e-14)


def test_flat_geometry_matches_rig_builder() -> None:
    K21 = RNG.uniform(40, 100, 15)
    K22 = RNG.uniform(20, 60, 15)
    H = RNG.uniform(0.5, 1.0, 15)
    X = RNG.uniform(0.1, 0.9, 15)
    A = sens.structure_matrices(sens.flat_geometry(K21, K22, H, X))
    for i in range(15):
        np.testing.assert_allclose(
            A[i], _A_of(rigs.flat_rig(K21[i], K22[i], H[i], X[i])), atol=1e-14
        )


def test_broadcasting_grid_shape() -> None:
    k1, k3 = np.array([0.2, 0.3]), np.array([0.05, 0.075, 0.1])
    A = sens.structure_matrices(sens.cubic_geometry(k1[:, None], 0.1, k3))
    assert A.shape == (2, 3, 6, 8)
    for i in range(2):  # each grid entry is the rig builder's matrix for its own (k1, k2, k3)
        for j in range(3):
            np.testing.assert_allclose(
                A[i, j], _A_of(rigs.cubic_rig(k1[i], 0.1, k3[j])), atol=1e-14
            )


def test_S_closed_form_equals_pinv_by_hand() -> None:
    # Closed form: T = Tmid + A^+ (w - A Tmid), so dT = T0 - Tw = A^+ W_ext exactly.
    rig = rigs.cubic_rig(0.15, 0.075, 0.075)
    A = _A_of(rig)
    for W in ([60.949, 0, 0, 0, 0, 0], [0, 32.183, 0, 0, 0, 0], [5, -3, 8, 0.4, -0.2, 0.3]):
        expected = np.linalg.norm(np.linalg.pinv(A) @ np.asarray(W, float)) / 8
        res = sens.sensitivity_of_rig(rig, W, "closed-form")
        assert res.S_N == pytest.approx(expected, rel=1e-10)
        assert bool(res.feasible)


def test_sensitivity_value_eq12_by_hand() -> None:
    # dT = (8, 0, ..., 0): S = sqrt((8/8)^2) = 1; dT = all 2: S = sqrt(8 * (2/8)^2) = 0.7071...
    assert sens.sensitivity_value(np.r_[8.0, np.zeros(7)]) == pytest.approx(1.0)
    assert sens.sensitivity_value(np.full(8, 2.0)) == pytest.approx(np.sqrt(8) * 0.25)


def _qp(
    A: np.ndarray, w: np.ndarray, lo: np.ndarray, hi: np.ndarray, ref: np.ndarray
) -> np.ndarray:
    """min |T - ref|^2 s.t. A T = w, lo <= T <= hi (quadprog)."""
    m = A.shape[1]
    C = np.hstack([A.T, np.eye(m), -np.eye(m)])
    b = np.concatenate([w, lo, -hi])
    return quadprog.solve_qp(np.eye(m), np.array(ref, dtype=float), C, b, meq=A.shape[0])[0]


@pytest.mark.parametrize(
    ("rig", "W"),
    [
        (rigs.flat_rig(51, 28, 0.67, 0.5), [1.7, 0.4, 9.4, 0.05, -0.09, 0.05]),
        (rigs.flat_rig(61, 34, 0.72, 0.5, t_max_N=285.0), [0.5, -1.0, 4.0, 0.0, 0.02, -0.01]),
        (rigs.cubic_rig(0.15, 0.075, 0.1), [70.043, 0, 0, 0, 0, 0]),
        (rigs.cubic_rig(0.3, 0.2, 0.05, Z_m=0.5), [0, 75.706, 0, 0, 0, 3.0]),
    ],
)
def test_S_exact_and_penalty_against_quadprog(rig, W) -> None:
    A = _A_of(rig)
    G = sens.gravity_load(rig.mass_kg)
    lo, hi = rig.t_min_N, rig.t_max_N
    W = np.asarray(W, float)
    for method, ref, tol in (("exact", 0.5 * (lo + hi), 1e-6), ("penalty", lo, 1e-4)):
        T0 = _qp(A, -G, lo, hi, ref)
        Tw = _qp(A, -(G + W), lo, hi, ref)
        expected = np.linalg.norm(T0 - Tw) / 8
        res = sens.sensitivity_of_rig(rig, W, method)
        assert bool(res.feasible)
        assert res.S_N == pytest.approx(expected, abs=tol), method
        np.testing.assert_allclose(res.delta_T_N, T0 - Tw, atol=10 * tol)


def test_penalty_differs_from_exact_when_bounds_are_active() -> None:
    # The penalty method pushes tensions to Tmin, so bounds are active and S differs from A^+ W.
    rig = rigs.flat_rig(51, 28, 0.67, 0.5)
    W = [1.7, 0.4, 9.4, 0.05, -0.09, 0.05]
    s_pen = sens.sensitivity_of_rig(rig, W, "penalty").S_N
    s_lin = np.linalg.norm(np.linalg.pinv(_A_of(rig)) @ np.asarray(W)) / 8
    assert abs(s_pen - s_lin) > 0.05 * s_lin


def test_batched_sensitivity_equals_single_configuration_path() -> None:
    k = np.sort(RNG.uniform(0.025, 0.4, size=(12, 3)), axis=1)[:, ::-1]
    W = np.array([[48.327, 0, 0, 0, 0, 0], [0, 19.041, 0, 0, 0, 0], [0, 60.949, 0, 0, 0, 6.0]])
    A = sens.structure_matrices(sens.cubic_geometry(k[:, 0], k[:, 1], k[:, 2]))
    G = sens.gravity_load(5.0)
    for method in ("exact", "improved-closed-form", "penalty", "closed-form"):
        res = sens.sensitivity(A[:, None], W, G, 35.0, 1000.0, method)
        assert res.S_N.shape == (12, 3)
        for i in range(12):
            one = sens.sensitivity_of_rig(rigs.cubic_rig(*k[i]), W, method)
            tol = 1e-5 if method == "penalty" else 1e-9  # penalty: chunk-wide stopping test
            np.testing.assert_allclose(res.S_N[i], one.S_N, rtol=tol)
            np.testing.assert_array_equal(res.feasible[i], one.feasible)


def test_singular_configurations_detected() -> None:
    G = sens.gravity_load(5.0)
    W = np.array([[60.0, 0, 0, 0, 0, 0], [0, 0, 0, 0, 6.0, 0]])
    cases = [
        ((0.15, 0.075, 0.075), "cube", True),  # the paper's optimum: k2 = k3 removes Mx
        ((0.2, 0.2, 0.1), "cube", True),  # k1 = k2 removes Mz
        ((0.15, 0.15, 0.15), "crossed", True),  # k1 = k3 removes My
        ((0.3, 0.1, 0.3), "crossed", True),
        ((0.15, 0.075, 0.075), "crossed", False),
        ((0.2, 0.2, 0.1), "crossed", False),  # crossed is regular at k1 = k2
    ]
    for k, layout, singular in cases:
        A = sens.structure_matrices(sens.cubic_geometry(*k, layout=layout))
        assert (np.linalg.matrix_rank(A, tol=1e-9) < 6) == singular  # independent check
        assert bool(sens.rank_deficient(A)) == singular, (k, layout)
        res = sens.sensitivity(A, W, G, 35.0, 1000.0, "exact")
        assert np.all(res.singular == singular)
        assert np.all(np.isnan(res.S_N) == singular)
        assert not np.any(res.feasible & singular)


def test_near_singular_drives_S_along_the_lost_direction_only() -> None:
    # crossed, k1 = k2 = 0.15, k3 -> k1: My is lost; S(My) ~ 1/gap, S(Fx) stays finite.
    G = sens.gravity_load(5.0)
    W = np.array([[60.0, 0, 0, 0, 0, 0], [0, 0, 0, 0, 6.0, 0]])
    gaps = np.array([1e-2, 1e-3, 1e-4])
    A = sens.structure_matrices(sens.cubic_geometry(0.15, 0.15, 0.15 - gaps))
    res = sens.sensitivity(A[:, None], W, G, 35.0, 1e9, "closed-form")
    assert not res.singular.any()
    ratio = res.S_N[:-1, 1] / res.S_N[1:, 1]
    np.testing.assert_allclose(ratio, 0.1, rtol=0.05)  # S(My) grows tenfold per decade
    assert np.ptp(res.S_N[:, 0]) < 0.05 * res.S_N[0, 0]
    smin = sens.singular_value_metrics(A).sigma_min
    np.testing.assert_allclose(smin[:-1] / smin[1:], 10.0, rtol=0.05)


def test_flat_rig_yaw_singularity_closed_form() -> None:
    # The flat rig of Table 3 has a singular surface inside its range (K22* ~ 24.9 for K21 = 51,
    # X = 0.5 m): check the formula with an SVD of the Rig builder's structure matrix.
    for K21, H, X in ((51, 0.67, 0.5), (61, 0.72, 0.5), (46, 0.92, 0.6), (80, 0.52, 0.7)):
        k22 = float(sens.flat_yaw_singular_K22(K21, X))
        assert 5 < k22 < 100
        s_at = np.linalg.svd(_A_of(rigs.flat_rig(K21, k22, H, X)), compute_uv=False)
        s_off = np.linalg.svd(_A_of(rigs.flat_rig(K21, k22 + 2, H, X)), compute_uv=False)
        assert s_at[-1] / s_at[0] < 1e-9
        assert s_off[-1] / s_off[0] > 1e-4
        # The lost direction is the yaw moment.
        u = np.linalg.svd(_A_of(rigs.flat_rig(K21, k22, H, X)))[0][:, -1]
        assert abs(u[5]) > 0.99


def test_singular_value_metrics_and_dW_bound() -> None:
    A = sens.structure_matrices(sens.cubic_geometry(0.15, 0.075, 0.075))
    met = sens.singular_value_metrics(A)
    s = np.linalg.svd(A, compute_uv=False)
    assert met.sigma_max == pytest.approx(s[0], rel=1e-10)
    assert met.sigma_min == pytest.approx(s[-1], rel=1e-8)
    assert met.condition == pytest.approx(s[0] / s[-1], rel=1e-8)
    # |A dT| / |dT| within [sigma_min, sigma_max] for dT in the row space of A.
    dT = A.T @ RNG.normal(size=(6, 200))
    r = np.linalg.norm(A @ dT, axis=0) / np.linalg.norm(dT, axis=0)
    assert r.min() >= met.sigma_min * (1 - 1e-9) and r.max() <= met.sigma_max * (1 + 1e-9)


def test_wrench_std_matches_foundation_covariance() -> None:
    rig = rigs.flat_rig(51, 28, 0.67, 0.5)
    q = np.concatenate([rig.reference_position_O_m, rig.reference_euler_rad])
    T = np.full(8, 150.0)
    cov = wrench_covariance(rig, q, T, 0.2, 0.0, tare_tensions_N=T + 1.0)
    std = sens.wrench_std(sens.structure_matrices(sens.flat_geometry(51, 28, 0.67, 0.5)), 0.2)
    np.testing.assert_allclose(std, cov.std, rtol=1e-9)
    full = sens.wrench_covariance(_A_of(rig), 0.2, tare=False)
    np.testing.assert_allclose(full, 0.04 * _A_of(rig) @ _A_of(rig).T, rtol=1e-12, atol=1e-15)


def test_feasibility_margin_against_quadprog() -> None:
    rig = rigs.cubic_rig(0.15, 0.075, 0.075)
    A = _A_of(rig)
    G = sens.gravity_load(5.0)
    loads = np.array([[75.706, 0, 0, 0, 0, 0], [0, -75.706, 0, 0, 0, 0]])
    lo, hi = rig.t_min_N, rig.t_max_N
    slacks = []
    for W in np.vstack([np.zeros(6), loads]):
        T = _qp(A, -(G + W), lo, hi, 0.5 * (lo + hi))
        slacks.append(np.minimum(T - lo, hi - T).min())
    margin = sens.feasibility_margin(A, G, loads, 35.0, 1000.0, "exact")
    assert margin == pytest.approx(min(slacks), abs=1e-6)
    # Tight limits: infeasible somewhere -> negative margin.
    assert sens.feasibility_margin(A, G, loads * 20, 35.0, 100.0, "exact") < 0


def test_aero_wrench_by_hand() -> None:
    C = [0.08, 0.02, 0.45, 0.01, -0.05, 0.01]
    W = sens.aero_wrench(40.0, C, rho_kgpm3=1.2, S_ref_m2=0.02, span_m=0.25, chord_m=0.08)
    q = 0.5 * 1.2 * 1600.0  # 960 Pa
    np.testing.assert_allclose(
        W, q * 0.02 * np.array([0.08, 0.02, 0.45, 0.25 * 0.01, 0.08 * -0.05, 0.25 * 0.01])
    )


@pytest.mark.parametrize(
    ("call", "name"),
    [
        (lambda: sens.cubic_geometry(0.0, 0.1, 0.1), "k1"),
        (lambda: sens.cubic_geometry(0.2, 1.2, 0.1), "k2"),
        (lambda: sens.cubic_geometry(0.2, 0.1, np.nan), "k3"),
        (lambda: sens.cubic_geometry(0.2, 0.1, 0.1, Z_m=1.39), "Z_m"),
        (lambda: sens.cubic_geometry(0.2, 0.1, 0.1, layout="star"), "layout"),
        (lambda: sens.flat_geometry(0.5, 28, 0.67), "K21"),
        (lambda: sens.flat_geometry(51, 28, -0.67), "H_m"),
        (lambda: sens.flat_geometry(51, 28, 0.67, 1.2), "X_m"),
        (lambda: sens.aero_wrench(-1.0, np.zeros(6), S_ref_m2=1, span_m=1, chord_m=1), "V_mps"),
        (lambda: sens.wrench_std(np.zeros((6, 8)), -0.1), "sigma_T_N"),
        (
            lambda: sens.sensitivity(np.zeros((6, 8)), np.zeros(6), np.zeros(6), 1, 2, "magic"),
            "method",
        ),
    ],
)
def test_bad_parameters_rejected(call, name: str) -> None:
    with pytest.raises(InputError, match=name):
        call()
