"""The fast path of ``exact`` for m = n + 2 (shared pivot order, one-line polygon certificates).

Independent references: quadprog (Goldfarb-Idnani) per pose, and a brute-force enumeration of the
polygon's candidate points (feet of the origin on every line, every pair of lines crossing) for the
one-line certificate.  The general kernel behind the fast path is counted, so that a test fails if
the fast path silently stops handling the poses.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import quadprog

from cdpr.analysis import tension as tn
from cdpr.analysis.dynamics import gravity_wrench
from cdpr.analysis.errors import InputError
from cdpr.analysis.kinematics import structure_matrix_at
from cdpr.analysis.rigs import paper_rigs
from cdpr.analysis.rotations import rotation_from_euler


def _poses_of_one_rig(rng: np.random.Generator, n: int):
    """A perturbed copy of the paper's cubic rig (anchors +-10 cm, platform points +-2 cm): poses
    within 5 cm / 5 deg of its reference pose, w = -(G + W_ext) with loads up to 800 N / 60 N m
    (about half infeasible), per-pose and per-cable limits."""
    rig = paper_rigs()["cubic_optimum"]
    anchors = rig.anchors_O_m + rng.uniform(-0.1, 0.1, (8, 3))
    attach = rig.attach_P_m + rng.uniform(-0.02, 0.02, (8, 3))
    pose = np.empty((n, 6))
    pose[:, :3] = rig.reference_position_O_m + rng.uniform(-0.05, 0.05, (n, 3))
    pose[:, 3:] = np.deg2rad(rng.uniform(-5.0, 5.0, (n, 3)))
    A = structure_matrix_at(anchors, attach, pose)
    G = gravity_wrench(rig.mass_kg, rig.com_P_m, rotation_from_euler(pose[:, 3:]))
    W = np.concatenate([rng.uniform(-800, 800, (n, 3)), rng.uniform(-60, 60, (n, 3))], 1)
    lo = rig.t_min_N + rng.uniform(0.0, 15.0, (n, 8))
    hi = rig.t_max_N - rng.uniform(0.0, 0.25, (n, 8)) * (rig.t_max_N - rig.t_min_N)
    return A, -(G + W), lo, hi


def _quadprog(A, w, lo, hi, ref):
    """min |T - ref| s.t. A T = w, lo <= T <= hi per pose; NaN rows where quadprog finds none."""
    T = np.full(lo.shape, np.nan)
    m = A.shape[-1]
    for k in range(A.shape[0]):
        C = np.vstack([A[k], np.eye(m), -np.eye(m)]).T
        b = np.concatenate([w[k], lo[k], -hi[k]])
        try:
            T[k] = quadprog.solve_qp(np.eye(m), ref[k], C, b, meq=A.shape[1])[0]
        except ValueError:
            pass
    return T


@pytest.fixture
def general_kernel_poses(monkeypatch):
    """Counts the poses that reach the general kernel (deferred by the fast path)."""
    seen = []
    orig = tn._exact_kernel

    def counting(At, *args):
        seen.append(At.shape[-1])
        return orig(At, *args)

    monkeypatch.setattr(tn, "_exact_kernel", counting)
    return seen


@pytest.mark.parametrize("chunk", [97, 5000])
def test_fast_path_matches_quadprog_on_perturbed_rigs(chunk, monkeypatch, general_kernel_poses):
    monkeypatch.setattr(tn, "CHUNK", chunk)
    rng = np.random.default_rng(11)
    n_total = n_feasible = 0
    for _ in range(4):  # one rig per batch: the pivot order is shared within a batch
        A, w, lo, hi = _poses_of_one_rig(rng, 250)
        for ref in (0.5 * (lo + hi), lo):
            T_qp = _quadprog(A, w, lo, hi, ref)
            feas = ~np.isnan(T_qp[:, 0])
            res = tn.exact(A, w, lo, hi, t_ref_N=ref)
            assert np.array_equal(res.feasible, feas), np.flatnonzero(res.feasible != feas)
            assert np.all(res.status[~feas] == tn.SOLVE_INFEASIBLE)
            assert np.abs(res.tensions_N[feas] - T_qp[feas]).max() <= 1e-6
            n_total += feas.size
            n_feasible += int(feas.sum())
    assert 0.2 * n_total <= n_feasible <= 0.8 * n_total  # both verdicts well represented
    # the fast path did the work: measured 0.3 % of the poses deferred with T_ref = T_mid and
    # ~7 % with T_ref = t_min (the optimum is then more often off the most violated line)
    assert sum(general_kernel_poses) <= 0.06 * n_total


def _flat_rig_poses(rng: np.random.Generator, n: int):
    """The paper's flat rig near its reference pose (+-2 cm, +-2 deg, aero loads +-20 N, +-0.5 N m)."""
    rig = paper_rigs()["flat_optimum"]
    pose = np.empty((n, 6))
    pose[:, :3] = rig.reference_position_O_m + rng.uniform(-0.02, 0.02, (n, 3))
    pose[:, 3:] = np.deg2rad(rng.uniform(-2.0, 2.0, (n, 3)))
    A = structure_matrix_at(rig.anchors_O_m, rig.attach_P_m, pose)
    G = gravity_wrench(rig.mass_kg, rig.com_P_m, rotation_from_euler(pose[:, 3:]))
    W = np.concatenate([rng.uniform(-20, 20, (n, 3)), rng.uniform(-0.5, 0.5, (n, 3))], 1)
    lo, hi = np.broadcast_to(rig.t_min_N, (n, 8)), np.broadcast_to(rig.t_max_N, (n, 8))
    return A, -(G + W), lo, hi


def test_pivot_order_is_chosen_again_when_the_rig_changes(monkeypatch, general_kernel_poses):
    """Two rigs in one batch (cubic, then flat): the pivot order chosen on the batch's sample does
    not suit the flat rig's poses; it is chosen again from the first chunk where more than 1/8 of
    the poses are rejected, so about one chunk (not all 600 flat-rig poses, measured with the
    order kept) goes to the general kernel."""
    monkeypatch.setattr(tn, "CHUNK", 100)
    rng = np.random.default_rng(5)
    parts = [_poses_of_one_rig(rng, 600), _flat_rig_poses(rng, 600)]
    A, w, lo, hi = (np.concatenate([p[i] for p in parts]) for i in range(4))
    res = tn.exact(A, w, lo, hi)
    T_qp = _quadprog(A, w, lo, hi, 0.5 * (lo + hi))
    feas = ~np.isnan(T_qp[:, 0])
    assert np.array_equal(res.feasible, feas)
    assert np.abs(res.tensions_N[feas] - T_qp[feas]).max() <= 1e-6
    assert sum(general_kernel_poses) <= 200


def _brute_force_polygon(n1, n2, lo_, hi_, tol):
    """Closest point to 0 of {lam: lo_ - tol <= n1 lam1 + n2 lam2 <= hi_ + tol} by enumerating
    the feet of 0 on the 2m lines and the crossings of every pair of lines; None if empty."""
    G = np.stack([n1, n2], axis=1)  # (m, 2)
    lines = [(G[j], lo_[j] - tol) for j in range(len(n1))] + [
        (G[j], hi_[j] + tol) for j in range(len(n1))
    ]
    cands = [g * c / (g @ g) for g, c in lines]
    for (g1, c1), (g2, c2) in itertools.combinations(lines, 2):
        M = np.array([g1, g2])
        if abs(np.linalg.det(M)) > 1e-12:
            cands.append(np.linalg.solve(M, [c1, c2]))
    slack = 1e-9 * (1.0 + np.abs(lo_).max() + np.abs(hi_).max())
    ok = [
        x
        for x in cands
        if np.all(G @ x >= lo_ - tol - slack) and np.all(G @ x <= hi_ + tol + slack)
    ]
    if not ok:
        return None
    return min(ok, key=lambda x: x @ x)


def test_one_line_certificates_against_brute_force():
    rng = np.random.default_rng(3)
    K, m = 1500, 8
    Q = np.linalg.qr(rng.normal(size=(K, m, m)))[0][:, :, :2]  # orthonormal null-space bases
    n1, n2 = Q[:, :, 0].T.copy(), Q[:, :, 1].T.copy()
    lo_ = rng.uniform(-1.5, 0.4, (m, K))
    hi_ = lo_ + rng.uniform(0.4, 3.0, (m, K))
    keep = ((lo_ > 1e-9) | (hi_ < -1e-9)).any(axis=0)  # 0 violates some limit: as it is used
    n1, n2, lo_, hi_ = n1[:, keep], n2[:, keep], lo_[:, keep], hi_[:, keep]
    K = int(keep.sum())
    tol = np.full(K, 1e-9)
    with np.errstate(all="ignore"):  # as in the caller: parallel lines give inf/nan
        lam1, lam2, state = tn._polygon_one_line(n1, n2, lo_, hi_, tol)
    n_found = n_empty = 0
    for k in range(K):
        ref = _brute_force_polygon(n1[:, k], n2[:, k], lo_[:, k], hi_[:, k], 1e-9)
        if state[k] == 0:
            assert ref is not None, k
            np.testing.assert_allclose([lam1[k], lam2[k]], ref, atol=1e-7)
            n_found += 1
        elif state[k] == 1:
            assert ref is None, k
            n_empty += 1
    assert n_found >= 100 and n_empty >= 100, (n_found, n_empty)
    assert np.mean(state == 2) <= 0.15  # the rest goes to the exhaustive line scan


def test_non_finite_structure_matrix_raises_on_the_fast_path():
    rng = np.random.default_rng(1)
    A, w, lo, hi = _poses_of_one_rig(rng, 50)
    for bad in (np.nan, np.inf):
        A_bad = A.copy()
        A_bad[17, 3, 5] = bad
        with pytest.raises(InputError, match="A: expected finite values"):
            tn.exact(A_bad, w, lo, hi)
    with pytest.raises(InputError, match="A: expected finite values"):
        tn.exact(np.full((6, 8), np.nan), np.zeros((4, 6)), np.ones(8), np.full(8, 9.0))


def test_empty_batch_and_batch_constant_wrench():
    r = tn.exact(np.zeros((0, 6, 8)), np.zeros((0, 6)), np.ones(8), np.full(8, 9.0))
    assert r.tensions_N.shape == (0, 8) and r.feasible.shape == (0,) and r.status.shape == (0,)
    rng = np.random.default_rng(2)
    A, w, lo, hi = _poses_of_one_rig(rng, 40)
    res = tn.exact(A, w[0], lo, hi)  # one wrench for every pose
    T_qp = _quadprog(A, np.broadcast_to(w[0], w.shape), lo, hi, 0.5 * (lo + hi))
    feas = ~np.isnan(T_qp[:, 0])
    assert np.array_equal(res.feasible, feas) and feas.any()
    assert np.abs(res.tensions_N[feas] - T_qp[feas]).max() <= 1e-6


def _polygon_by_quadprog(n1, n2, lo_, hi_):
    """Closest point to 0 of {lam: lo_ <= n1 lam1 + n2 lam2 <= hi_} by quadprog; None if empty."""
    G = np.stack([n1, n2], axis=1)  # (m, 2)
    try:
        return quadprog.solve_qp(np.eye(2), np.zeros(2), np.vstack([G, -G]).T, np.r_[lo_, -hi_])[0]
    except ValueError:
        return None


def test_polygon_with_narrow_strips_against_quadprog():
    """Polygons where 1-4 cables are strips narrower than 1e-5 (the null-space picture of limit
    ranges narrower than 1e-5 N): both polygon kernels against quadprog in the 2-D null space.
    Choosing the candidate of least norm (the former rule) was 6.8e-8 off here (and 4e-5 N in
    tensions on the cubic rig's narrow ranges): the vertex of a strip with a constraint relaxed by
    tol beats the optimum by ~|lam| tol in norm^2, and the norm^2 of points sqrt(|lam| tol) apart
    differ by that little.  Now 6e-13."""
    rng = np.random.default_rng(8)
    K, m = 1500, 8
    Q = np.linalg.qr(rng.normal(size=(K, m, m)))[0][:, :, :2]
    n1, n2 = Q[:, :, 0].T.copy(), Q[:, :, 1].T.copy()
    lam0 = rng.normal(0.0, 100.0, (2, K))  # a point the narrow strips pass through
    through = n1 * lam0[0] + n2 * lam0[1]
    lo_ = rng.uniform(-200.0, 30.0, (m, K))
    hi_ = lo_ + rng.uniform(60.0, 400.0, (m, K))
    narrow = np.argsort(rng.random((m, K)), axis=0) < rng.integers(1, 5, K)
    width = 10 ** rng.uniform(-8.0, -5.0, (m, K))
    start = through - rng.uniform(0.05, 0.95, (m, K)) * width
    lo_ = np.where(narrow, start, lo_)
    hi_ = np.where(narrow, start + width, hi_)
    keep = ((lo_ > 1e-9) | (hi_ < -1e-9)).any(axis=0)  # 0 violates some limit: as it is used
    n1, n2, lo_, hi_ = n1[:, keep], n2[:, keep], lo_[:, keep], hi_[:, keep]
    K = int(keep.sum())
    tol = np.full(K, 4e-10)  # as exact relaxes for limits up to 400 N
    lam1, lam2, found = tn._polygon(n1, n2, lo_, hi_, tol)
    with np.errstate(all="ignore"):
        f1, f2, state = tn._polygon_one_line(n1, n2, lo_, hi_, tol)
    n_found = 0
    worst = 0.0
    for k in range(K):
        ref = _polygon_by_quadprog(n1[:, k], n2[:, k], lo_[:, k], hi_[:, k])
        assert found[k] == (ref is not None), k
        if ref is None:
            assert state[k] != 0
            continue
        n_found += 1
        worst = max(worst, np.abs([lam1[k], lam2[k]] - ref).max())
        if state[k] == 0:
            np.testing.assert_allclose([f1[k], f2[k]], ref, atol=1e-7)
    print(f"general polygon vs quadprog: max |d lam| {worst:.1e} over {n_found} polygons")
    assert n_found >= 250 and worst <= 1e-9


@pytest.mark.parametrize("chunk", [97, 5000])
def test_fast_path_with_narrow_limits_matches_quadprog(chunk, monkeypatch, general_kernel_poses):
    """Perturbed cubic rigs (one per batch) with 1-4 cables narrowed to 1e-8 .. 1e-5 N around
    quadprog's optimum (T_ref kept): quadprog's verdict and tensions within 1e-6 N (1.8e-6 N off
    before the polygon's certified choice), and the fast path still answers most poses (measured:
    65 of 343 to the general kernel, for uncertified lines and conditioning)."""
    monkeypatch.setattr(tn, "CHUNK", chunk)
    rng = np.random.default_rng(12)
    n_total = 0
    for _ in range(3):
        A, w, lo, hi = _poses_of_one_rig(rng, 300)
        mid = 0.5 * (lo + hi)
        T_wide = _quadprog(A, w, lo, hi, mid)
        ok = ~np.isnan(T_wide[:, 0])
        A, w, lo, hi, mid, T_wide = A[ok], w[ok], lo[ok], hi[ok], mid[ok], T_wide[ok]
        K = A.shape[0]
        narrow = np.argsort(rng.random((K, 8)), axis=1) < rng.integers(1, 5, (K, 1))
        width = 10 ** rng.uniform(-8.0, -5.0, (K, 8))
        at_lo, at_hi = T_wide - lo < 1e-7, hi - T_wide < 1e-7
        start = np.where(
            at_lo,
            lo,
            np.where(at_hi, hi - width, T_wide - rng.uniform(0.05, 0.95, (K, 8)) * width),
        )
        lo_n, hi_n = np.where(narrow, start, lo), np.where(narrow, start + width, hi)
        T_qp = _quadprog(A, w, lo_n, hi_n, mid)
        feas = ~np.isnan(T_qp[:, 0])
        assert feas.all()  # the optimum stays where it was
        res = tn.exact(A, w, lo_n, hi_n, t_ref_N=mid)
        assert res.feasible.all()
        assert np.abs(res.tensions_N - T_qp).max() <= 1e-6
        n_total += K
    assert n_total >= 300
    print(f"general kernel: {sum(general_kernel_poses)} of {n_total} poses")
    assert sum(general_kernel_poses) <= 0.3 * n_total
