"""Tension distribution near singularity: accurate or flagged, the same verdict in any batch.

The expected optimum comes from ``tests/_singular_cases.py`` (KKT conditions by construction,
independent of the solver) and is cross-checked with quadprog; the smallest singular value of
``A'`` (A with unit-norm rows) is computed here with numpy's SVD.
"""

from __future__ import annotations

import numpy as np
import pytest
from _singular_cases import singular_cases
from test_tension_oracle import quadprog_solve, rig_cases

from cdpr.analysis import tension as tn
from cdpr.analysis.errors import InputError

OPT_TOL_N = 1e-6


def _sigma_unit(A: np.ndarray) -> np.ndarray:
    rn = np.linalg.norm(A, axis=-1, keepdims=True)
    return np.linalg.svd(A / rn, compute_uv=False)[..., -1]


@pytest.mark.parametrize("sigma", [1e-2, 1e-4, 2e-5, 1.2e-5, 6e-6, 1e-7, 0.0])
def test_exact_is_within_1e_6_of_the_optimum_or_flagged(sigma):
    A, w, lo, hi, ref, T_opt = singular_cases(sigma, 300, seed=int(sigma * 1e7) + 3)
    r = tn.exact(A, w, lo, hi, t_ref_N=ref)
    s = _sigma_unit(A)
    flagged = r.status == tn.STATUS_RANK_DEFICIENT
    assert np.all(~r.feasible[flagged])
    # the verdict is the rank test on sigma_min(A') and nothing else
    np.testing.assert_array_equal(flagged, s < tn.RANK_TOL)
    # every feasible case here is feasible (T_opt is), so nothing else may be reported
    assert np.all(r.status[~flagged] == tn.STATUS_OK)
    err = np.abs(r.tensions_N - T_opt).max(axis=-1)
    assert np.all(err[~flagged] <= OPT_TOL_N), (sigma, err[~flagged].max())
    # quadprog agrees with the constructed optimum on the accepted cases
    for k in np.flatnonzero(~flagged)[:25]:
        qp = quadprog_solve(A[k], w[k], lo[k], hi[k], ref[k])
        assert qp is not None
        assert np.abs(qp - r.tensions_N[k]).max() <= 2 * OPT_TOL_N


def test_every_method_flags_rank_5_structure_matrices():
    A, w, lo, hi, _, _ = singular_cases(0.0, 300, seed=5)
    for name in tn.METHODS:
        r = tn.distribute(name, A, w, lo, hi)
        assert np.all(r.status == tn.STATUS_RANK_DEFICIENT), name
        assert not r.feasible.any(), name


def test_rank_verdict_does_not_depend_on_the_batch(monkeypatch):
    """Rank-5 and barely-full-rank poses among flat-rig poses (the fast path's batch): the status
    of each pose equals its status alone, for several batch sizes, positions and chunk sizes."""
    A, w, lo, hi = rig_cases("flat_optimum", 120, 9)
    As, ws, los, his, _, _ = singular_cases(0.0, 10, seed=21)
    Ab, wb, lob, hib, _, _ = singular_cases(1.3e-5, 10, seed=22)
    scale = np.linalg.norm(A[0], axis=-1, keepdims=True)  # rig-sized rows: same A' after scaling
    odd_A = np.concatenate([As, Ab]) * scale
    odd_w = np.concatenate([ws, wb]) * scale[..., 0]
    odd_lo, odd_hi = np.concatenate([los, lob]), np.concatenate([his, hib])
    alone = np.array([tn.exact(odd_A[k], odd_w[k], odd_lo[k], odd_hi[k]).status for k in range(20)])
    assert np.all(alone[:10] == tn.STATUS_RANK_DEFICIENT)
    assert np.all(alone[10:] != tn.STATUS_RANK_DEFICIENT)
    rng = np.random.default_rng(3)
    for size, chunk in ((21, 5000), (60, 7), (140, 5000)):
        monkeypatch.setattr(tn, "CHUNK", chunk)
        k = rng.permutation(size)
        pick = rng.choice(120, size - 20, replace=False)
        batch = [np.concatenate([x[pick], y])[k] for x, y in ((A, odd_A), (w, odd_w))]
        bl, bh = (np.concatenate([x[pick], y])[k] for x, y in ((lo, odd_lo), (hi, odd_hi)))
        for name in tn.METHODS:
            r = tn.distribute(name, batch[0], batch[1], bl, bh)
            where = np.argsort(k)[size - 20 :]  # positions of the 20 odd poses in the batch
            if name == "exact":
                np.testing.assert_array_equal(r.status[where], alone)
            rd = r.status[where] == tn.STATUS_RANK_DEFICIENT
            np.testing.assert_array_equal(rd, np.arange(20) < 10, err_msg=name)


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
