"""Tension distribution on small problems solved by hand, plus the contract's edge cases.

Hand derivations (KKT: ``T - T_ref = A^T nu + mu_lo - mu_hi`` with ``mu >= 0`` on active bounds):

1-DOF, 3 cables (m = n + 2), ``A = [[1, -1, 1]]``, limits [0, 10] except ``t_max_3 = 4``, w = 12:
  T_mid = (5, 5, 2); closed form ``T = T_mid + a (w - a.T_mid)/3 = (25/3, 5/3, 16/3)`` violates
  ``T_3 <= 4``.  Clamping T_3 = 4: ``T_1 - T_2 = 8``, min ``(T_1-5)^2 + (T_2-5)^2`` gives (9, 1):
  exact T = (9, 1, 4), nu = 4, mu_hi3 = 2 >= 0.  With T_ref = t_min = 0: closed form (4, -4, 4);
  T_2 = 0 and T_3 = 4 active give T = (8, 0, 4), nu = 8, mu_lo2 = 8, mu_hi3 = 4.
  w = 17 > max(T_1 - T_2 + T_3) = 14: infeasible.
1-DOF, 2 cables (m = n + 1), ``A = [[1, -1]]``, t_min = (1, 2), t_max = (10, 10):
  w = 8: closed form ``T_mid + a (8 + 0.5)/2 = (9.75, 1.75)`` violates T_2 >= 2; T = (10, 2).
  w = 9: T_2 >= 2 forces T_1 >= 11 > 10: infeasible.
Planar point, 4 cables to (+-1, +-1) (m = n + 2), ``u_1 = (1, 1)/sqrt2, u_2 = (-1, 1)/sqrt2,
u_3 = (-1, -1)/sqrt2, u_4 = (1, -1)/sqrt2``, limits [0, 10] but [1.5, 8.5] for cable 1 (all
  T_mid = 5), w = (8 sqrt2, 0): ``A A^T = 2 I``, closed form ``5 + (u_i . w)/2 = (9, 1, 1, 9)``
  violates T_1 <= 8.5.  With
  T_1 = 8.5 the two equilibrium equations for d = T_{2,3,4} - 5 are ``-d2 - d3 + d4 = 12.5``,
  ``d2 - d3 - d4 = -3.5``; the min-norm d = B^T (B B^T)^-1 r = (-4, -4.5, 4): T = (8.5, 1, 0.5, 9),
  and mu_hi1 = a_1.nu - 3.5 = 1 >= 0.
"""

from __future__ import annotations

import numpy as np
import pytest

from cdpr.analysis import tension as tn
from cdpr.analysis.errors import InputError

S2 = np.sqrt(2.0)
PLANAR_A = np.array([[1.0, -1.0, -1.0, 1.0], [1.0, 1.0, -1.0, -1.0]]) / S2
ALL = ("closed-form", "improved-closed-form", "penalty", "exact")


def test_one_dof_three_cables_by_hand():
    A = np.array([[1.0, -1.0, 1.0]])
    lo, hi = np.zeros(3), np.array([10.0, 10.0, 4.0])
    cf = tn.closed_form(A, [12.0], lo, hi)
    np.testing.assert_allclose(cf.tensions_N, [25 / 3, 5 / 3, 16 / 3], atol=1e-12)
    assert not cf.feasible and cf.max_violation_N == pytest.approx(16 / 3 - 4)
    ex = tn.exact(A, [12.0], lo, hi)
    np.testing.assert_allclose(ex.tensions_N, [9.0, 1.0, 4.0], atol=1e-9)
    assert ex.feasible and ex.status == tn.SOLVE_OK
    icf = tn.improved_closed_form(A, [12.0], lo, hi)
    np.testing.assert_allclose(icf.tensions_N, [9.0, 1.0, 4.0], atol=1e-9)
    assert icf.feasible
    ex0 = tn.exact(A, [12.0], lo, hi, t_ref_N=lo)
    np.testing.assert_allclose(ex0.tensions_N, [8.0, 0.0, 4.0], atol=1e-9)
    pen = tn.penalty(A, [12.0], lo, hi)
    np.testing.assert_allclose(pen.tensions_N, [8.0, 0.0, 4.0], atol=1e-6)
    bad = tn.exact(A, [17.0], lo, hi)
    assert not bad.feasible and bad.status == tn.SOLVE_INFEASIBLE


def test_one_dof_two_cables_interval_by_hand():
    A = np.array([[1.0, -1.0]])
    lo, hi = np.array([1.0, 2.0]), np.array([10.0, 10.0])
    ex = tn.exact(A, [[8.0], [9.0], [3.0]], lo, hi)
    np.testing.assert_allclose(ex.tensions_N[0], [10.0, 2.0], atol=1e-9)
    np.testing.assert_allclose(ex.tensions_N[2], [7.25, 4.25], atol=1e-9)  # closed form inside
    assert ex.feasible.tolist() == [True, False, True]
    assert ex.status.tolist() == [tn.SOLVE_OK, tn.SOLVE_INFEASIBLE, tn.SOLVE_OK]


def test_planar_point_four_cables_by_hand():
    w = np.array([8 * S2, 0.0])
    lo, hi = np.array([1.5, 0.0, 0.0, 0.0]), np.array([8.5, 10.0, 10.0, 10.0])
    cf = tn.closed_form(PLANAR_A, w, lo, hi)
    np.testing.assert_allclose(cf.tensions_N, [9.0, 1.0, 1.0, 9.0], atol=1e-12)
    for name in ("exact", "improved-closed-form"):
        r = tn.distribute(name, PLANAR_A, w, lo, hi)
        np.testing.assert_allclose(r.tensions_N, [8.5, 1.0, 0.5, 9.0], atol=1e-9)
        assert r.feasible
    # max x force with w_y = 0: T_4 = T_1 + T_2 - T_3, f_x sqrt2 = 2 T_1 - 2 T_3 <= 17
    assert tn.exact(PLANAR_A, [17 / S2 - 1e-6, 0.0], lo, hi).feasible
    assert not tn.exact(PLANAR_A, [17 / S2 + 1e-6, 0.0], lo, hi).feasible


def test_improved_closed_form_uses_each_cables_own_limits():
    """cdpyr's improved closed form picks wrong limits when per-cable limits differ.

    Planar case above with cable 3 in [0.4, 9.6] (T_mid still 5): the answer (8.5, 1, 0.5, 9)
    has T_4 = 9 above cable 1's t_max = 8.5, right only if every cable is checked against its own limits.
    1-DOF, 4 cables, ``A = [1 1 1 1]``, t_min = (0, 0, 6, 0), t_max = (2, 10, 10, 3), so
    T_mid = (1, 5, 8, 1.5) (sum 15.5), w = 24, by hand:
      closed form T_mid + 8.5/4 = (3.125, 7.125, 10.125, 3.625): violations 1.125, -, 0.125, 0.625
      -> clamp T_1 = 2; free (2, 3, 4): T_mid + (22 - 14.5)/3 = (7.5, 10.5, 4): violations 0.5, 1
      -> clamp T_4 = 3; free (2, 3): (5, 8) + (19 - 13)/2 = (8, 11) -> clamp T_3 = 10; T_2 = 9.
    Limits shifted after a removal (cable 2 checked against cable 1's t_max = 2) or cable 1's
    limits for all would end elsewhere.
    """
    w = np.array([8 * S2, 0.0])
    lo = np.array([1.5, 0.0, 0.4, 0.0])
    hi = np.array([8.5, 10.0, 9.6, 10.0])
    r = tn.improved_closed_form(PLANAR_A, w, lo, hi)
    np.testing.assert_allclose(r.tensions_N, [8.5, 1.0, 0.5, 9.0], atol=1e-9)
    assert r.feasible and r.max_violation_N == 0.0
    wrong = tn.improved_closed_form(PLANAR_A, w, np.full(4, lo[0]), np.full(4, hi[0]))
    assert not np.allclose(wrong.tensions_N, r.tensions_N, atol=1e-3)

    A = np.ones((1, 4))
    lo4, hi4 = np.array([0.0, 0.0, 6.0, 0.0]), np.array([2.0, 10.0, 10.0, 3.0])
    r = tn.improved_closed_form(A, [12.0], lo4, hi4)  # closed form T_mid - 0.875: inside
    np.testing.assert_allclose(r.tensions_N, [0.125, 4.125, 7.125, 0.625], atol=1e-12)
    r = tn.improved_closed_form(A, [24.0], lo4, hi4)
    np.testing.assert_allclose(r.tensions_N, [2.0, 9.0, 10.0, 3.0], atol=1e-9)
    assert r.feasible and r.status == tn.SOLVE_OK
    # w = 26 needs T_2 = 11 > 10 after the three clamps: one free cable left -> gives up
    r = tn.improved_closed_form(A, [26.0], lo4, hi4)
    assert not r.feasible and r.status == tn.SOLVE_GAVE_UP


def test_rank_deficient_structure_matrix_is_flagged_not_raised():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(3, 6, 8))
    A[1, 5] = 0.0  # pose 1: a zero row, rank 5
    A[2, 5] = A[2, 4]  # pose 2: two equal rows
    w = rng.normal(size=(3, 6))
    for name in ALL:
        r = tn.distribute(name, A, w, np.full(8, 1.0), np.full(8, 100.0))
        assert not r.feasible[1] and not r.feasible[2]
        if name != "penalty":
            assert r.status[1] == tn.SOLVE_RANK_DEFICIENT, name
            assert r.status[2] == tn.SOLVE_RANK_DEFICIENT, name
        assert np.all(np.isfinite(r.residual_N))


def test_broadcasting_leading_dims_and_per_pose_limits():
    A = np.broadcast_to(PLANAR_A, (2, 3, 2, 4))
    w = np.zeros((2, 3, 2))
    w[..., 0] = np.linspace(0, 12, 6).reshape(2, 3)
    lo = np.zeros((2, 3, 4))
    hi = np.full((2, 3, 4), 10.0)
    lo[1, 2, 0], hi[1, 2, 0] = 1.5, 8.5
    w[1, 2] = [8 * S2, 0.0]
    for name in ALL:
        r = tn.distribute(name, A, w, lo, hi)
        assert r.tensions_N.shape == (2, 3, 4) and r.feasible.shape == (2, 3)
    ex = tn.exact(A, w, lo, hi)
    np.testing.assert_allclose(ex.tensions_N[1, 2], [8.5, 1.0, 0.5, 9.0], atol=1e-9)
    np.testing.assert_allclose(ex.tensions_N[0, 0], [5.0, 5.0, 5.0, 5.0], atol=1e-12)
    # one structure matrix, many wrenches
    r = tn.exact(PLANAR_A, w.reshape(-1, 2), np.zeros(4), np.full(4, 10.0))
    assert r.tensions_N.shape == (6, 4)


def test_bad_input_is_one_clear_error():
    with pytest.raises(InputError, match="t_min_N < t_max_N"):
        tn.exact(PLANAR_A, [0.0, 0.0], np.full(4, 5.0), np.full(4, 5.0))
    with pytest.raises(InputError, match="method"):
        tn.distribute("simplex", PLANAR_A, [0.0, 0.0], np.zeros(4), np.ones(4))
    with pytest.raises(InputError, match="m - n <= 2"):
        tn.exact(np.ones((1, 4)), [1.0], np.zeros(4), np.ones(4))
    with pytest.raises(InputError, match="unsupported options"):
        tn.distribute("closed-form", PLANAR_A, [0.0, 0.0], np.zeros(4), np.ones(4), t_ref_N=1)
    with pytest.raises(InputError, match="t_ref_N"):
        tn.exact(PLANAR_A, [0.0, 0.0], np.zeros(4), np.ones(4), t_ref_N=np.zeros(3))
