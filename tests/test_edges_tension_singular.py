"""Tension distribution near singularity: accurate or flagged, the same verdict in any batch.

The expected optimum comes from ``tests/_singular_cases.py`` (KKT conditions by construction,
independent of the solver) or from quadprog; the singular values are computed here with numpy's
SVD, and the rank floor from the formula docs/tension.md states (``floor_from_spec``).

The floor is relative to the problem's scale: ``2 eps scale / 1e-6 N`` with ``scale = sqrt(m) max
|t_min, t_max, t_ref|`` (3.8e-7 for limits up to 300 N).  It applies to sigma_min of A with unit
rows, and for ``exact`` also to ``sigma_F``, the same restricted to the cables not at a limit: at a
vertex of two nearly parallel limits the answer is ill-conditioned in a well-conditioned pose.
"""

from __future__ import annotations

import numpy as np
import pytest
import quadprog
from _singular_cases import (
    floor_from_spec,
    sigma_free,
    singular_cases,
    vertex_cases,
    with_sigma_min,
)
from test_tension_oracle import (
    quadprog_solve_orthonormal,
    random_geometry_cases,
    rig_cases,
)

from cdpr.analysis import tension as tn
from cdpr.analysis.errors import InputError

OPT_TOL_N = 1e-6


def _sigma_unit(A: np.ndarray) -> np.ndarray:
    rn = np.linalg.norm(A, axis=-1, keepdims=True)
    return np.linalg.svd(A / rn, compute_uv=False)[..., -1]


def test_rank_floor_is_the_documented_formula():
    rng = np.random.default_rng(4)
    lo = rng.uniform(0.0, 50.0, (40, 8))
    hi = lo + 10 ** rng.uniform(0.0, 9.0, (40, 1)) * rng.uniform(0.5, 1.0, (40, 8))
    ref = 0.5 * (lo + hi)
    np.testing.assert_allclose(tn.rank_floor(lo, hi), floor_from_spec(lo, hi, ref), rtol=1e-12)
    np.testing.assert_allclose(tn.rank_floor(lo, hi, lo), floor_from_spec(lo, hi, lo), rtol=1e-12)
    # 300 N limits: 3.8e-7; an upper limit of 1e9 N standing for "none" caps it at 4.4e-6
    assert tn.rank_floor(np.full(8, 35.0), np.full(8, 300.0)) == pytest.approx(3.77e-7, rel=0.01)
    assert tn.rank_floor(np.full(8, 35.0), np.full(8, 1e9)) == pytest.approx(4.44e-6, rel=0.01)


@pytest.mark.parametrize("sigma", [1e-2, 1e-4, 2.1e-6, 6e-7, 1e-7, 0.0])
def test_exact_is_within_1e_6_of_the_optimum_or_flagged(sigma):
    A, w, lo, hi, ref, T_opt = singular_cases(sigma, 300, seed=int(sigma * 1e7) + 3)
    r = tn.exact(A, w, lo, hi, t_ref_N=ref)
    floor = floor_from_spec(lo, hi, ref)
    at = (np.abs(T_opt - lo) < 1e-9) | (np.abs(T_opt - hi) < 1e-9)  # the constructed active set
    s_F = sigma_free(A, at)
    flagged = r.status == tn.SOLVE_RANK_DEFICIENT
    assert np.all(~r.feasible[flagged])
    # the verdict is the rank test on sigma_F (sigma_min(A') when no cable is at a limit), up
    # to a band around the floor where the answer's own active set decides
    clear = (s_F < floor / 1.3) | (s_F > 1.3 * floor)
    np.testing.assert_array_equal(flagged[clear], (s_F < floor)[clear])
    # every case here is feasible (T_opt is), so nothing else may be reported
    assert np.all(r.status[~flagged] == tn.SOLVE_OK)
    err = np.abs(r.tensions_N - T_opt).max(axis=-1)
    assert np.all(err[~flagged] <= OPT_TOL_N), (sigma, err[~flagged].max())
    # quadprog agrees with the constructed optimum on the accepted cases
    for k in np.flatnonzero(~flagged)[:25]:
        qp = quadprog_solve_orthonormal(A[k], w[k], lo[k], hi[k], ref[k])
        assert qp is not None
        assert np.abs(qp - r.tensions_N[k]).max() <= OPT_TOL_N
    if sigma == 2.1e-6:  # the issue's pose: solved, no longer flagged (was all 300)
        assert flagged.mean() <= 0.05, flagged.sum()


@pytest.mark.parametrize("sigma_G", [1e-3, 1e-5, 1e-6, 1e-7, 1e-9])
def test_exact_flags_an_ill_conditioned_vertex_in_a_well_conditioned_pose(sigma_G):
    """sigma_min(A') is ~0.5 for every case here; the optimum sits on two limits whose lines are
    nearly parallel, so the six other cables' matrix is near singular.  Accepted answers are within
    1e-6 N of the constructed optimum; the flag follows sigma_F, not sigma_min(A')."""
    A, w, lo, hi, ref, T_opt, active = vertex_cases(sigma_G, 120, seed=int(-np.log10(sigma_G)))
    assert _sigma_unit(A).min() > 0.1
    r = tn.exact(A, w, lo, hi, t_ref_N=ref)
    floor = floor_from_spec(lo, hi, ref)
    s_F = sigma_free(A, active)
    flagged = r.status == tn.SOLVE_RANK_DEFICIENT
    clear = (s_F < floor / 1.3) | (s_F > 1.3 * floor)
    np.testing.assert_array_equal(flagged[clear], (s_F < floor)[clear])
    assert np.all(r.status[~flagged] == tn.SOLVE_OK)
    err = np.abs(r.tensions_N - T_opt).max(axis=-1)
    assert np.all(err[~flagged] <= OPT_TOL_N), err[~flagged].max()
    for k in np.flatnonzero(~flagged)[:20]:
        qp = quadprog_solve_orthonormal(A[k], w[k], lo[k], hi[k], ref[k])
        assert qp is not None and np.abs(qp - r.tensions_N[k]).max() <= OPT_TOL_N
    if sigma_G == 1e-9:  # sigma_F ~ 1e-10 throughout: all flagged
        assert flagged.all()


def _near_singular_rig_cases(source: str, n: int, seed: int, band: tuple[float, float]):
    """Poses of a real rig (or random geometries) moved to sigma_min(A') = band x the floor
    (log-uniform), per-case per-cable limits, half the wrenches balanced by random tensions within
    the limits (feasible by construction), half the rig's own aero loads (mostly infeasible once A
    is near singular)."""
    if source == "random_geometry":
        A, w, lo, hi = random_geometry_cases(n, seed)
    else:
        A, w, lo, hi = rig_cases(source, n, seed)
    rng = np.random.default_rng(seed + 100)
    floor = floor_from_spec(lo, hi, 0.5 * (lo + hi))
    A = with_sigma_min(A, floor * np.exp(rng.uniform(*np.log(band), n)))
    balanced = rng.random(n) < 0.5
    T0 = rng.uniform(lo, hi)
    w = np.where(balanced[:, None], np.einsum("kij,kj->ki", A, T0), w)
    return A, w, lo, hi, balanced


@pytest.mark.parametrize("source", ["flat_optimum", "cubic_optimum", "random_geometry"])
@pytest.mark.parametrize("band", [(1.0, 4.0), (4.0, 1e3)], ids=["floor-4x", "4x-1000x"])
def test_exact_matches_quadprog_on_near_singular_rig_poses(source, band):
    """Same verdict as quadprog and tensions within 1e-6 N on every pose not flagged, with
    T_ref = T_mid and t_min; the flags are few and all at an answer within 1.3x of the floor."""
    A, w, lo, hi, balanced = _near_singular_rig_cases(source, 300, 17, band)
    for ref in (0.5 * (lo + hi), lo):
        r = tn.exact(A, w, lo, hi, t_ref_N=ref)
        flagged = r.status == tn.SOLVE_RANK_DEFICIENT
        T_qp = [quadprog_solve_orthonormal(A[k], w[k], lo[k], hi[k], ref[k]) for k in range(300)]
        feas = np.array([t is not None for t in T_qp])
        assert np.all(feas[balanced])  # quadprog solves what is feasible by construction
        ok = ~flagged
        np.testing.assert_array_equal(r.feasible[ok], feas[ok])
        both = np.flatnonzero(ok & feas)
        err = np.array([np.abs(r.tensions_N[k] - T_qp[k]).max() for k in both])
        print(f"{source} {band}: flagged {flagged.sum()}, max |dT| {err.max():.1e} N")
        assert err.max() <= OPT_TOL_N
        assert feas[ok].sum() >= 100 and (~feas[ok]).sum() >= 50  # both verdicts well represented
        # a flag is never far from the floor: sigma_F at quadprog's answer is below 1.3x of it
        for k in np.flatnonzero(flagged & feas):
            at = (np.abs(T_qp[k] - lo[k]) < 1e-8) | (np.abs(T_qp[k] - hi[k]) < 1e-8)
            floor = floor_from_spec(lo[k], hi[k], ref[k])
            assert sigma_free(A[k : k + 1], at[None])[0] < 1.3 * floor
        if band[0] >= 4.0:
            assert flagged.mean() <= 0.02


def test_issue_pose_at_sigma_2_1e_6_is_solved_like_quadprog():
    """The issue's report: flagged at sigma_min(A') = 2.1e-6 while quadprog solves it.  Flat and
    cubic rig poses moved there (wrenches balanced by tensions within the limits): quadprog's
    verdict and tensions within 1e-6 N; the only flags left are answers on a pair of limits whose
    six other cables' matrix is below the floor (sigma_F at quadprog's answer, numpy SVD)."""
    for source in ("flat_optimum", "cubic_optimum"):
        A, w, lo, hi = rig_cases(source, 200, 31)
        A = with_sigma_min(A, 2.1e-6)
        np.testing.assert_allclose(_sigma_unit(A), 2.1e-6, rtol=1e-3)
        T0 = np.random.default_rng(5).uniform(lo, hi)
        w = np.einsum("kij,kj->ki", A, T0)
        r = tn.exact(A, w, lo, hi)
        flagged = r.status == tn.SOLVE_RANK_DEFICIENT
        assert np.all(r.feasible == ~flagged) and flagged.sum() <= 4, flagged.sum()
        mid = 0.5 * (lo + hi)
        for k in range(200):
            qp = quadprog_solve_orthonormal(A[k], w[k], lo[k], hi[k], mid[k])
            assert qp is not None
            if flagged[k]:
                at = (np.abs(qp - lo[k]) < 1e-8) | (np.abs(qp - hi[k]) < 1e-8)
                floor = floor_from_spec(lo[k], hi[k], mid[k])
                assert sigma_free(A[k : k + 1], at[None])[0] < 1.3 * floor
            else:
                assert np.abs(qp - r.tensions_N[k]).max() <= OPT_TOL_N


def test_closed_forms_near_singular_poses_match_quadprog():
    """Down to the floor the closed form and the improved closed form solve ill-conditioned poses
    from the SVD: the closed form is quadprog's equality-only optimum within 1e-6 N (it was 2e-2 N
    off at sigma 1e-6 from the normal equations)."""
    A, w, lo, hi, balanced = _near_singular_rig_cases("flat_optimum", 200, 23, (2.0, 100.0))
    cf = tn.closed_form(A, w, lo, hi)
    assert np.all(cf.status != tn.SOLVE_RANK_DEFICIENT)
    mid = 0.5 * (lo + hi)
    for k in np.flatnonzero(balanced):  # the aero loads need tensions of 1e6 N here
        rn = np.linalg.norm(A[k], axis=-1)
        U, s, Vt = np.linalg.svd(A[k] / rn[:, None], full_matrices=False)
        ref = quadprog.solve_qp(np.eye(8), mid[k], Vt.T, (U.T @ (w[k] / rn)) / s, meq=6)[0]
        assert np.abs(cf.tensions_N[k] - ref).max() <= OPT_TOL_N
    icf = tn.improved_closed_form(A, w, lo, hi)
    T_qp = [quadprog_solve_orthonormal(A[k], w[k], lo[k], hi[k], mid[k]) for k in range(200)]
    n_checked = 0
    for k in np.flatnonzero(icf.feasible):
        assert T_qp[k] is not None
        at = np.isclose(icf.tensions_N[k], lo[k]) | np.isclose(icf.tensions_N[k], hi[k])
        if at.sum() <= 1:  # one clamp or none: the exact optimum
            assert np.abs(icf.tensions_N[k] - T_qp[k]).max() <= OPT_TOL_N
            n_checked += 1
    assert n_checked >= 50


def test_penalty_flags_poses_its_weight_cannot_hold():
    """The penalty method holds A' T = w' with weight lambda sigma_min^2 along the weakest
    direction: below lambda_max sigma^2 = 1 (sigma 1e-5 for the default schedule) it flags."""
    A, w, lo, hi = rig_cases("flat_optimum", 40, 8)
    for sigma, flagged in ((3e-6, True), (3e-5, False)):
        r = tn.penalty(with_sigma_min(A, sigma), w, lo, hi)
        assert np.all((r.status == tn.SOLVE_RANK_DEFICIENT) == flagged), sigma
    r = tn.penalty(with_sigma_min(A, 3e-5), w, lo, hi, lambdas=(1.0, 1e2, 1e4, 1e6))
    assert np.all(r.status == tn.SOLVE_RANK_DEFICIENT)  # 1 / sqrt(1e6) = 1e-3


def test_every_method_flags_rank_5_structure_matrices():
    A, w, lo, hi, _, _ = singular_cases(0.0, 300, seed=5)
    for name in tn.METHODS:
        r = tn.distribute(name, A, w, lo, hi)
        assert np.all(r.status == tn.SOLVE_RANK_DEFICIENT), name
        assert not r.feasible.any(), name


def test_rank_verdict_does_not_depend_on_the_batch(monkeypatch):
    """Rank-5, barely-full-rank and ill-conditioned-vertex poses among flat-rig poses (the fast
    path's batch): the status of each pose equals its status alone, for several batch sizes,
    positions and chunk sizes.  The vertex poses (solved about T_mid here, not the constructed
    reference) are flagged or not by the answer's reduced matrix: whatever the verdict, the same in
    every batch."""
    A, w, lo, hi = rig_cases("flat_optimum", 120, 9)
    As, ws, los, his, _, _ = singular_cases(0.0, 10, seed=21)
    Ab, wb, lob, hib, _, _ = singular_cases(1.3e-5, 10, seed=22)
    Av, wv, lov, hiv, refv, _, act = vertex_cases(1e-8, 10, seed=23)  # sigma_F ~ 1e-9: flagged
    scale = np.linalg.norm(A[0], axis=-1, keepdims=True)  # rig-sized rows: same A' after scaling
    odd_A = np.concatenate([As, Ab, Av]) * scale
    odd_w = np.concatenate([ws, wb, wv]) * scale[..., 0]
    odd_lo, odd_hi = np.concatenate([los, lob, lov]), np.concatenate([his, hib, hiv])
    alone = np.array([tn.exact(odd_A[k], odd_w[k], odd_lo[k], odd_hi[k]).status for k in range(30)])
    assert np.all(alone[:10] == tn.SOLVE_RANK_DEFICIENT)
    assert np.all(alone[10:20] != tn.SOLVE_RANK_DEFICIENT)
    rank_5 = np.arange(30) < 10
    rng = np.random.default_rng(3)
    for size, chunk in ((31, 5000), (60, 7), (150, 5000)):
        monkeypatch.setattr(tn, "CHUNK", chunk)
        k = rng.permutation(size)
        pick = rng.choice(120, size - 30, replace=False)
        batch = [np.concatenate([x[pick], y])[k] for x, y in ((A, odd_A), (w, odd_w))]
        bl, bh = (np.concatenate([x[pick], y])[k] for x, y in ((lo, odd_lo), (hi, odd_hi)))
        where = np.argsort(k)[size - 30 :]  # positions of the 30 odd poses in the batch
        for name in tn.METHODS:
            r = tn.distribute(name, batch[0], batch[1], bl, bh)
            if name == "exact":
                np.testing.assert_array_equal(r.status[where], alone)
            rd = r.status[where] == tn.SOLVE_RANK_DEFICIENT
            np.testing.assert_array_equal(rd[:20], rank_5[:20], err_msg=name)


def test_batches_of_different_sizes_raise_input_error():
    A, w, lo, hi = rig_cases("flat_optimum", 5, 1)
    for name in tn.METHODS:
        with pytest.raises(InputError, match=r"w: batch shape \(4,\).*\(5,\).*A"):
            tn.distribute(name, A, w[:4], lo, hi)
        with pytest.raises(InputError, match=r"t_max_N: batch shape \(3,\)"):
            tn.distribute(name, A, w, lo, hi[:3])
    # one value shared by the batch still broadcasts
    r = tn.exact(A, w[:1], lo[0], hi[0])
    assert r.tensions_N.shape == (5, 8)
