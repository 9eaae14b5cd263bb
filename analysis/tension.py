"""Tension distribution: one contract, four methods, batched over poses.

Every method solves ``A T = w`` for cable tensions ``T`` (..., m) within per-cable limits
``t_min_N <= T <= t_max_N`` and returns a :class:`TensionResult`.  ``A`` is the structure matrix
(..., n, m) (n = 6 for a spatial rig) and ``w`` (..., n) the wrench the cables must apply on the
platform, which for a static platform is ``w = -(G + W_ext)`` (see :mod:`cdpr.analysis.dynamics`).
All methods are batched over the leading dimensions (no Python loop over poses: the batch is cut in
chunks of :data:`CHUNK` poses and each chunk is processed struct-of-arrays, batch index last) and
accept limits that differ per cable and per pose.

Objectives (named, because they differ):

- ``closed-form`` (Pott 2009): ``T = T_mid + A^+ (w - A T_mid)``, ``T_mid = (t_min + t_max)/2``, the
  min ``|T - T_mid|_2`` solution of the equality alone; feasible only if it respects the limits.
- ``improved-closed-form`` (Pott 2014): the closed form, then while a cable violates its limits,
  clamp the worst violator at the limit it violates, move its force to the wrench and re-solve the
  closed form for the remaining cables (each with its own ``T_mid``); fails when fewer than n cables
  would remain or the reduced matrix loses rank.  An approximation of min ``|T - T_mid|_2`` with the
  limits: when it succeeds after one clamp it is the exact optimum; after two or more it can be a
  feasible but sub-optimal point (docs/tension.md measures how often).
- ``penalty`` (the paper, eq. after (7)): min ``|T - T_min|_2^2 + lambda (|A' T - w'|^2 +
  |min(T - t_min, 0)|^2 + |max(T - t_max, 0)|^2)`` for an increasing schedule of lambda, warm
  started, each stage solved exactly by a semismooth Newton (active-set) iteration.  ``A'``, ``w'``
  are ``A``, ``w`` with unit-norm rows.  Converges to the exact min ``|T - T_min|_2`` as lambda grows.
- ``exact``: the exact min ``|T - T_ref|_2`` s.t. ``A T = w`` and the limits, ``T_ref = T_mid`` by
  default (``t_ref_N=t_min`` gives the penalty method's objective), for m - n <= 2 (null-space
  polygon: the closest point of a convex polygon to the origin); certifies infeasibility.  For
  m = n + 2 a fast path (elimination in a pivot order shared by the batch, one line of the
  polygon with a KKT or emptiness certificate) handles the poses it can certify.

Rank-deficient (or numerically singular, see :data:`RANK_TOL`) structure matrices do not raise:
the pose is flagged ``feasible=False`` with ``status == SOLVE_RANK_DEFICIENT``, by every method,
with a per-pose test (the same verdict alone and in any batch) relative to the problem's scale
(:func:`rank_floor`: where no double-precision answer is determined to :data:`ACCURACY_N` by the
data).  ``exact`` applies it to the structure matrix of the cables not at a limit at its answer
too, and solves the poses close to the floor from the SVD of ``A'`` (:data:`SVD_BELOW`), so its
answers stay within 1e-6 N of the optimum (and of quadprog) down to it; the closed forms use the
SVD there too, and ``penalty`` flags where its weight cannot hold the equations.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations
from typing import Any, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._checks import as_float_array, check_trailing
from .errors import InputError

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
IntArray = NDArray[np.int8]

SOLVE_OK = 0
"""Status code: a feasible solution was found."""
SOLVE_INFEASIBLE = 1
"""Status code: no tension distribution within the limits (certified by ``exact``) or the method's
answer violates the limits / equality."""
SOLVE_RANK_DEFICIENT = 2
"""Status code: the structure matrix (or the reduced one) is rank deficient at this pose."""
SOLVE_GAVE_UP = 3
"""Status code (improved closed form): clamping would leave fewer than n free cables."""
SOLVE_NAMES = {
    SOLVE_OK: "ok",
    SOLVE_INFEASIBLE: "infeasible",
    SOLVE_RANK_DEFICIENT: "rank-deficient structure matrix",
    SOLVE_GAVE_UP: "too few free cables left (improved closed form gave up)",
}
"""Human-readable meaning of each status code."""


@dataclass(frozen=True)
class TensionResult:
    """Result of a tension distribution over a batch of poses.

    tensions_N: (..., m) cable tensions, N.
    feasible: (...,) True when ``|A T - w| <= tol`` and every tension is within its limits.
    residual_N: (...,) equilibrium residual ``|A T - w|_2`` (N and N m mixed, as the norm of the
        wrench vector).
    max_violation_N: (...,) worst bound violation ``max(t_min - T, T - t_max, 0)``, N.
    objective: the objective this method minimises, e.g. ``"min |T - T_mid|_2"``.
    method: the method's registered name.
    status: (...,) int8 status code (see :data:`SOLVE_NAMES`), or None.
    """

    tensions_N: FloatArray
    feasible: BoolArray
    residual_N: FloatArray
    max_violation_N: FloatArray
    objective: str
    method: str
    status: IntArray | None = None


FEASIBILITY_TOL_N = 1e-6
"""Tolerance (N) on the residual and the bounds when a result is declared feasible, relative to
``1 + max |t_max|`` of the pose."""

CHUNK = 5000
"""Poses per chunk: bounds the working memory (well under 1 KiB per pose) and keeps it in cache."""

ACCURACY_N = 1e-6
"""What ``exact`` promises (N): its tensions are within this of the exact optimum of the problem as
given, or the pose is flagged ``SOLVE_RANK_DEFICIENT`` (see :data:`RANK_TOL`)."""

ACCURACY_REL = 1e-10
"""Beyond a scale of ``ACCURACY_N / ACCURACY_REL`` = 1e4 N (``scale_N``, :func:`rank_floor`) the
promise is relative: within ``ACCURACY_REL scale_N`` (1e-6 N of 1e4 N is all double precision
gives; an upper limit of 1e9 N standing for "none" must not flag every pose)."""

_EPS = float(np.finfo(np.float64).eps)

RANK_TOL = 2.0 * _EPS / ACCURACY_N
"""The rank test, relative to the problem's scale (per N, 4.4e-10): a pose is flagged
``SOLVE_RANK_DEFICIENT`` when ``sigma_min(A') < RANK_TOL * scale_N`` (:func:`rank_floor`), with
``A'`` = A with unit-norm rows and ``scale_N = sqrt(m) max_j max(|t_min_j|, |t_max_j|, |t_ref_j|)``,
which bounds both ``|T|_2`` and ``|T_ref|_2``.  ``exact`` also flags an answer whose *reduced*
matrix fails the same test: ``sigma_F``, the smallest singular value of ``A'`` restricted to the
cables not at a limit (the columns at a limit taken out), in place of ``sigma_min(A')``.

Why: an answer computed in double precision -- ``exact``'s, or quadprog's -- is the exact optimum of
data perturbed by a few eps, which moves the optimum by up to ``kappa eps scale_N / sigma_F``
(first order: the cables not at a limit solve ``A'_F T_F = w' - A'_S T_S``).  Measured against the
exact rational optimum of the stored data on 1690 near-singular problems (docs/tension.md):
``kappa <= 0.31`` for ``exact`` and <= 7 for quadprog given orthonormal equations, while
``sigma_min(A')`` in place of ``sigma_F`` gives ``kappa`` up to 3e5 (a vertex of two nearly
parallel limits is ill-conditioned in a well-conditioned pose).  At ``sigma_F >= RANK_TOL scale_N``
the bound ``eps scale_N / sigma_F`` is at most ``ACCURACY_N / 2``: ``exact`` was within 1e-7 N of
the optimum and 1e-6 N of quadprog there.  Below it quadprog is off by up to 2.7e-6 N (0.1 .. 1 x
the floor) and calls feasible problems infeasible (below 0.1 x).  The floor is 3.8e-7 for the flat
rig (limits up to 300 N), 1.3e-6 for the cubic rig (1000 N); :data:`ACCURACY_REL` caps it.

Decided per pose from the pose's own data, so the verdict never depends on the other poses of the
batch: a lower bound clears the well-conditioned poses (``sigma_min(A')`` from the Cholesky factor of
``A' A'^T``, ``sigma_F`` from it and the null-space rows of the cables at a limit, see
:func:`_free_sigma_low`), the others get their singular values (LAPACK SVD)."""

PIVOT_TOL = 1e-20
"""Floor of the Cholesky pivots of ``A' A'^T`` (diagonal 1): keeps a rank-deficient pose finite.  A
pose with a floored pivot never passes the Cholesky bound (:data:`_TRUST_BELOW`); the SVD decides."""

SVD_BELOW = 1e-3
"""``exact``: poses whose ``sigma_min(A')`` -- or, at a limit, ``sigma_F`` -- is not certified
above this are solved from the SVD of ``A'`` (error ~ eps |T| / sigma_min) instead of the normal
equations (error ~ eps |T| / sigma_min^2, and ~ eps |T| / (sigma_min sigma_F) at a vertex),
which keeps the answer within ``ACCURACY_N / 4`` down to the rank floor."""

_FLOOR_CAP = 2.0 * _EPS / ACCURACY_REL  # the largest rank floor (scales above 1e4 N), 4.4e-6
_TRUST_BELOW = 1e-6  # lower bounds of sigma below this are not trusted to clear a pose: SVD
_FAST_MARGIN = 1e4  # exact's fast path keeps a pose only with sigma_F certified >= this x floor
_REL_TOL = 1e-12  # exact: constraints relaxed by this times (1 + max t_max) when intersected
_NULL_TOL = 1e-20  # |null-space row|^2 below which a cable does not move in the null space
_TINY = 1e-280  # replaces 0 as a divisor: turns "parallel" constraints into +-huge bounds
_BIG = 1e100  # line parameters beyond this come from parallel, violated constraints


def check_problem(
    A: ArrayLike,
    w: ArrayLike,
    t_min_N: ArrayLike,
    t_max_N: ArrayLike,
    *,
    finite_A: bool = True,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Validate and broadcast a tension-distribution problem.

    Returns ``A`` (..., n, m), ``w`` (..., n), ``t_min`` (..., m), ``t_max`` (..., m) with common
    leading dimensions.  ``finite_A=False`` leaves the scan of A for NaN/inf to the caller.
    """
    A = as_float_array(A, "A")
    if A.ndim < 2:
        raise InputError(f"A: expected shape (..., n, m), got {A.shape}")
    n, m = A.shape[-2:]
    if finite_A:
        _check_finite_A(A)
    if m < n:
        raise InputError(f"A: expected at least as many cables as DOF (m >= n), got n={n}, m={m}")
    w = check_trailing(w, "w", (n,))
    t_min = check_trailing(t_min_N, "t_min_N", (m,))
    t_max = check_trailing(t_max_N, "t_max_N", (m,))
    lead = _lead_shape(
        ("A", A.shape[:-2]),
        ("w", w.shape[:-1]),
        ("t_min_N", t_min.shape[:-1]),
        ("t_max_N", t_max.shape[:-1]),
    )
    if np.any(t_min >= t_max):
        raise InputError("t_min_N, t_max_N: expected t_min_N < t_max_N for every cable")
    return (
        np.broadcast_to(A, lead + (n, m)),
        np.broadcast_to(w, lead + (n,)),
        np.broadcast_to(t_min, lead + (m,)),
        np.broadcast_to(t_max, lead + (m,)),
    )


def _lead_shape(*named: tuple[str, tuple[int, ...]]) -> tuple[int, ...]:
    """The common batch shape of the arguments, or :class:`InputError` naming the one that does
    not match (numpy's broadcasting error names neither argument)."""
    lead: tuple[int, ...] = ()
    owner = named[0][0]
    for name, shape in named:
        try:
            new = np.broadcast_shapes(lead, shape)
        except ValueError:
            raise InputError(
                f"{name}: batch shape {shape} does not match the batch shape {lead} of {owner} "
                "(expected equal batch sizes, or 1 to share one value)"
            ) from None
        if new != lead:
            lead, owner = new, name
    return lead


def sigma_min_unit_rows(A: ArrayLike) -> FloatArray:
    """Smallest singular value of A (..., n, m) with its rows scaled to unit norm (zero rows
    stay zero), the quantity the rank test compares with :func:`rank_floor`."""
    A = np.asarray(A, dtype=np.float64)
    rn = np.linalg.norm(A, axis=-1, keepdims=True)
    As = np.divide(A, rn, out=np.zeros_like(A), where=rn > 0)
    if As.size == 0:
        return np.zeros(A.shape[:-2])
    return np.linalg.svd(As, compute_uv=False)[..., -1]


def rank_floor(
    t_min_N: ArrayLike, t_max_N: ArrayLike, t_ref_N: ArrayLike | None = None
) -> FloatArray:
    """The rank test's floor (...,) for limits (and reference) (..., m): a pose whose
    ``sigma_min_unit_rows(A)`` is below it is flagged ``SOLVE_RANK_DEFICIENT`` by every method.

    ``eps scale_N / max(ACCURACY_N, ACCURACY_REL scale_N)``, ``scale_N = sqrt(m) max_j
    max(|t_min_j|, |t_max_j|, |t_ref_j|)``: ``RANK_TOL scale_N`` up to a scale of 1e4 N, then
    ``eps / ACCURACY_REL`` (see :data:`RANK_TOL`)."""
    lo = np.asarray(t_min_N, dtype=np.float64)
    hi = np.asarray(t_max_N, dtype=np.float64)
    big = np.maximum(np.abs(lo), np.abs(hi))
    if t_ref_N is not None:
        big = np.maximum(big, np.abs(np.asarray(t_ref_N, dtype=np.float64)))
    return _floor_of_scale(np.sqrt(big.shape[-1]) * big.max(axis=-1))


def _floor_soa(lo: FloatArray, hi: FloatArray, ref: FloatArray | None = None) -> FloatArray:
    """:func:`rank_floor` (C,) of struct-of-arrays limits (m, C)."""
    big = np.maximum(np.abs(lo), np.abs(hi))
    if ref is not None:
        big = np.maximum(big, np.abs(ref))
    return _floor_of_scale(np.sqrt(big.shape[0]) * big.max(axis=0))


def _floor_of_scale(scale_N: FloatArray) -> FloatArray:
    out: FloatArray = np.minimum(RANK_TOL * scale_N, _FLOOR_CAP)
    return out


class _RankFloor:
    """The rank floor of a chunk's poses (struct-of-arrays limits (m, C) or (m, 1), optional
    reference), computed only for the poses that ask: a pose whose lower bound of sigma clears
    the largest floor there can be, ``max(_FLOOR_CAP, at_least)``, never needs its own."""

    def __init__(
        self,
        lo: FloatArray,
        hi: FloatArray,
        ref: FloatArray | None = None,
        at_least: float = 0.0,
        idx: NDArray[np.intp] | None = None,
    ) -> None:
        self.lo, self.hi, self.ref, self.at_least, self.idx = lo, hi, ref, at_least, idx
        self.cap = max(_FLOOR_CAP, at_least)

    def at(self, k: NDArray[np.intp]) -> FloatArray:
        """The floor (K,) of the poses k."""
        j = k if self.idx is None else self.idx[k]
        ref = None if self.ref is None else _take_cols(self.ref, j)
        fl = _floor_soa(_take_cols(self.lo, j), _take_cols(self.hi, j), ref)
        return np.maximum(np.broadcast_to(fl, j.shape), self.at_least)

    def sub(self, k: NDArray[np.intp]) -> _RankFloor:
        """The floors of the poses k, as their own chunk."""
        j = k if self.idx is None else self.idx[k]
        return _RankFloor(self.lo, self.hi, self.ref, self.at_least, j)


def _rank_ok(As: FloatArray, bound: FloatArray, floors: _RankFloor) -> BoolArray:
    """Per pose: sigma_min(As) >= its rank floor, for As (n, m, C) (unit rows).  ``bound`` (C,) is
    a lower bound of sigma_min; the floor is computed only where it does not clear the largest
    floor, and the SVD runs only where it does not clear the pose's own."""
    ok = bound >= max(4.0 * floors.cap, _TRUST_BELOW)
    unsure = np.flatnonzero(~ok)
    if unsure.size:
        fl = floors.at(unsure)
        ok[unsure] = bound[unsure] >= np.maximum(4.0 * fl, _TRUST_BELOW)
        left = ~ok[unsure]
        if left.any():
            k = unsure[left]
            sv = np.linalg.svd(np.moveaxis(_take(As, k), -1, 0), compute_uv=False)
            ok[k] = sv[:, -1] >= fl[left]
    return ok


def _check_finite_A(A: FloatArray) -> None:
    if not np.all(np.isfinite(_compact(A))):
        raise InputError("A: expected finite values, got NaN or inf")


def finish(
    A: FloatArray,
    w: FloatArray,
    T: FloatArray,
    t_min: FloatArray,
    t_max: FloatArray,
    objective: str,
    method: str,
    ok: BoolArray | None = None,
) -> TensionResult:
    """Compute residual, violation and the feasible flag, and pack a :class:`TensionResult`."""
    res = np.linalg.norm(np.einsum("...ij,...j->...i", A, T) - w, axis=-1)
    viol = np.maximum(np.maximum(t_min - T, T - t_max).max(axis=-1), 0.0)
    scale = 1.0 + np.abs(t_max).max(axis=-1)
    feasible = (res <= FEASIBILITY_TOL_N * scale) & (viol <= FEASIBILITY_TOL_N * scale)
    if ok is not None:
        feasible &= ok
    status = np.where(feasible, SOLVE_OK, SOLVE_INFEASIBLE).astype(np.int8)
    return TensionResult(T, feasible, res, viol, objective, method, status)


# ---------------------------------------------------------------------------------------------
# Batch plumbing: flatten the leading dims, cut in chunks, go struct-of-arrays (batch index last).


def _flat(x: FloatArray, k: int) -> FloatArray:
    """(lead..., *trailing k dims) -> (N, *trailing); no copy when possible."""
    return x.reshape((-1,) + x.shape[x.ndim - k :])


def _soa(x: FloatArray, s: int, e: int) -> FloatArray:
    """Rows s:e of a (N, ...) array as a contiguous (..., C) array, or (..., 1) if constant."""
    if x.strides[0] == 0:  # broadcast along the batch: keep one copy
        return np.ascontiguousarray(x[0][..., None])
    return np.ascontiguousarray(np.moveaxis(x[s:e], 0, -1))


def _compact(x: FloatArray) -> FloatArray:
    """x without its broadcast (zero-stride) leading dimensions, which become length 1."""
    return x[tuple(slice(0, 1) if st == 0 else slice(None) for st in x.strides[:-1])]


def _ref_from_options(lo: FloatArray, hi: FloatArray, t_ref_N: ArrayLike | None) -> FloatArray:
    if t_ref_N is None:  # once per distinct row, broadcast like lo and hi
        return np.broadcast_to(0.5 * (_compact(lo) + _compact(hi)), lo.shape)
    ref = check_trailing(t_ref_N, "t_ref_N", (lo.shape[-1],))
    return np.broadcast_to(ref, np.broadcast_shapes(ref.shape, lo.shape))


class _Factor:
    """Row-equilibrated Cholesky factor of ``A' A'^T`` for a chunk, struct-of-arrays.

    ``A' = diag(rs) A`` has unit-norm rows (this changes neither ``{T: A T = w}`` nor the
    min-norm solution, and makes the normal equations well scaled).  ``L`` (n, n, C) is lower
    triangular with ``L L^T = A' A'^T``; ``inv_diag`` (n, C) holds ``1 / L_jj``.  The loops run
    over the n rows only; each step is one numpy call over the whole chunk.
    """

    def __init__(self, At: FloatArray, floors: _RankFloor) -> None:
        n, _, C = At.shape
        rn = np.sqrt(np.einsum("imc,imc->ic", At, At))
        self.rs = np.divide(1.0, rn, out=np.zeros_like(rn), where=rn > 0)
        self.As = At * self.rs[:, None, :]
        G = np.einsum("imc,jmc->ijc", self.As, self.As)
        L = np.zeros((n, n, C))
        inv_diag = np.empty((n, C))
        for j in range(n):
            p = G[j, j] - np.einsum("kc,kc->c", L[j, :j], L[j, :j]) if j else G[0, 0]
            d = np.sqrt(np.maximum(p, PIVOT_TOL))
            L[j, j] = d
            inv_diag[j] = 1.0 / d
            if j + 1 < n:
                v = G[j + 1 :, j]
                if j:
                    v = v - np.einsum("ikc,kc->ic", L[j + 1 :, :j], L[j, :j])
                L[j + 1 :, j] = v * inv_diag[j]
        self.L = L
        self.inv_diag = inv_diag
        self.n = n
        # sigma_min(A')^2 = lambda_min(G) >= 1 / trace(G^-1) = 1 / |L^-1|_F^2 >= lambda_min / n:
        # a lower bound within sqrt(n) of sigma_min, from one triangular solve
        Linv = self.forward(np.broadcast_to(np.eye(n)[:, :, None], (n, n, C)))
        self.floor = 1.0 / np.sqrt(np.einsum("ijc,ijc->c", Linv, Linv))
        self.floors = floors
        self.ok = _rank_ok(self.As, self.floor, floors)

    def subset(self, idx: NDArray[np.intp]) -> _Factor:
        """The factor of the poses ``idx`` of the chunk."""
        sub = object.__new__(_Factor)
        sub.rs, sub.As, sub.n = _take(self.rs, idx), _take(self.As, idx), self.n
        sub.L, sub.inv_diag = _take(self.L, idx), _take(self.inv_diag, idx)
        sub.ok, sub.floor, sub.floors = self.ok[idx], self.floor[idx], self.floors.sub(idx)
        return sub

    def forward(self, r: FloatArray) -> FloatArray:
        """``z = L^-1 r`` for r (n, ...) with the batch last."""
        L, inv_diag = self.L, self.inv_diag
        z = np.empty(np.broadcast_shapes(r.shape, inv_diag.shape))
        z[0] = r[0] * inv_diag[0]
        for i in range(1, self.n):
            z[i] = (r[i] - np.einsum("k...,k...->...", L[i, :i], z[:i])) * inv_diag[i]
        return z

    def backward(self, z: FloatArray) -> FloatArray:
        """``y = L^-T z`` for z (n, C)."""
        L, inv_diag, n = self.L, self.inv_diag, self.n
        y = np.empty_like(z)
        y[n - 1] = z[n - 1] * inv_diag[n - 1]
        for i in range(n - 2, -1, -1):
            y[i] = (z[i] - np.einsum("kc,kc->c", L[i + 1 :, i], y[i + 1 :])) * inv_diag[i]
        return y

    def pinv(self, r: FloatArray) -> FloatArray:
        """``A^+ r`` (m, C) for r (n, C) in the units of the unscaled rows."""
        y = self.backward(self.forward(r * self.rs))
        return np.einsum("imc,ic->mc", self.As, y)

    def closest(self, At: FloatArray, w: FloatArray, ref: FloatArray) -> FloatArray:
        """``T_p = ref + A^+ (w - A ref)`` (m, C): from the normal equations, or from the SVD of
        ``A'`` for the poses whose sigma_min is not certified above :data:`SVD_BELOW`."""
        Tp = ref + self.pinv(w - _apply(At, np.broadcast_to(ref, At.shape[1:])))
        weak = np.flatnonzero(self.ok & (self.floor < SVD_BELOW))
        if weak.size:
            ref_k = _take(np.broadcast_to(ref, Tp.shape), weak)
            Tp[:, weak] = _svd_solve(self, weak, _take(w, weak), _take(At, weak), ref_k)[0]
        return Tp

    def orthonormal_rows(self) -> FloatArray:
        """``B = L^-1 A'`` (n, m, C): orthonormal rows spanning the row space of A."""
        L, inv_diag = self.L, self.inv_diag
        B = np.empty_like(self.As)
        B[0] = self.As[0] * inv_diag[0]
        for i in range(1, self.n):
            B[i] = (self.As[i] - np.einsum("kc,kmc->mc", L[i, :i], B[:i])) * inv_diag[i]
        return B


def _take(x: Any, idx: NDArray[np.intp]) -> Any:
    """Batch entries ``idx`` of a batch-last array, as a contiguous array (fancy indexing on the
    last axis would give a strided one)."""
    return np.take(x, idx, axis=-1)


def _apply(At: FloatArray, T: FloatArray) -> FloatArray:
    """``A T`` (n, C) for At (n, m, C) and T (m, C)."""
    return np.einsum("imc,mc->ic", At, T)


def _summary(
    At: FloatArray, w: FloatArray, T: FloatArray, lo: FloatArray, hi: FloatArray
) -> tuple[FloatArray, FloatArray, BoolArray]:
    """Residual (C,), max violation (C,) and feasible (C,) of T (m, C), struct-of-arrays."""
    r = _apply(At, T) - w
    res = np.sqrt(np.einsum("ic,ic->c", r, r))
    viol = np.maximum(np.maximum(lo - T, T - hi).max(axis=0), 0.0)
    tol = FEASIBILITY_TOL_N * (1.0 + np.abs(hi).max(axis=0))
    return res, viol, (res <= tol) & (viol <= tol)


class _Chunked:
    """Runs a struct-of-arrays kernel chunk by chunk and assembles a :class:`TensionResult`."""

    def __init__(self, A: FloatArray, w: FloatArray, lo: FloatArray, hi: FloatArray) -> None:
        self.lead = A.shape[:-2]
        self.n, self.m = A.shape[-2:]
        self.A, self.w = _flat(A, 2), _flat(w, 1)
        self.lo, self.hi = _flat(lo, 1), _flat(hi, 1)
        self.N = self.A.shape[0]

    def run(
        self, kernel: Any, extra: tuple[FloatArray, ...], objective: str, method: str
    ) -> TensionResult:
        N, m = self.N, self.m
        T_out = np.empty((N, m))
        res_out = np.empty(N)
        viol_out = np.empty(N)
        feas_out = np.empty(N, dtype=bool)
        status_out = np.empty(N, dtype=np.int8)
        extra_f = tuple(_flat(x, 1) for x in extra)
        for s in range(0, N, CHUNK):
            e = min(N, s + CHUNK)
            At = _soa(self.A, s, e)
            if At.shape[-1] == 1 and e - s > 1:
                At = np.ascontiguousarray(np.broadcast_to(At, At.shape[:-1] + (e - s,)))
            # kernels index every column: expand batch-constant inputs to the chunk's width
            w, lo, hi, *ex_l = (
                np.ascontiguousarray(np.broadcast_to(x, x.shape[:-1] + (e - s,)))
                for x in (_soa(y, s, e) for y in (self.w, self.lo, self.hi, *extra_f))
            )
            ex = tuple(ex_l)
            T, status = kernel(At, w, lo, hi, *ex)
            res, viol, feas = _summary(At, w, T, lo, hi)
            feas &= status == SOLVE_OK
            status = np.where(feas | (status != SOLVE_OK), status, SOLVE_INFEASIBLE)
            T_out[s:e] = T.T
            res_out[s:e], viol_out[s:e], feas_out[s:e], status_out[s:e] = res, viol, feas, status
        lead = self.lead
        return TensionResult(
            T_out.reshape(lead + (m,)),
            feas_out.reshape(lead),
            res_out.reshape(lead),
            viol_out.reshape(lead),
            objective,
            method,
            status_out.reshape(lead).astype(np.int8),
        )


# ---------------------------------------------------------------------------------------------
# Closed form (Pott 2009)


def _closed_form_kernel(
    At: FloatArray, w: FloatArray, lo: FloatArray, hi: FloatArray
) -> tuple[FloatArray, IntArray]:
    f = _Factor(At, _RankFloor(lo, hi))
    T = f.closest(At, w, 0.5 * (lo + hi))
    status = np.where(f.ok, SOLVE_OK, SOLVE_RANK_DEFICIENT).astype(np.int8)
    return T, status


def closed_form(
    A: ArrayLike, w: ArrayLike, t_min_N: ArrayLike, t_max_N: ArrayLike
) -> TensionResult:
    """Pott's closed form: ``T = T_mid + A^+ (w - A T_mid)``, ``T_mid = (t_min + t_max)/2``.

    The minimiser of ``|T - T_mid|_2`` subject to ``A T = w`` only; feasible when it respects limits.
    From the normal equations, or from the SVD of ``A'`` where ``sigma_min(A')`` is not certified
    above :data:`SVD_BELOW` (the normal equations' error ~ eps |T| / sigma^2 would be 2e-2 N at
    sigma 1e-6).  A: (..., n, m); w: (..., n) (N, N m); t_min_N, t_max_N: (..., m) or (m,) (N).
    """
    A_, w_, lo, hi = check_problem(A, w, t_min_N, t_max_N)
    return _Chunked(A_, w_, lo, hi).run(
        _closed_form_kernel, (), "min |T - T_mid|_2 (equality only)", "closed-form"
    )


# ---------------------------------------------------------------------------------------------
# Improved closed form (Pott 2014)


def _improved_kernel(
    At: FloatArray, w: FloatArray, lo: FloatArray, hi: FloatArray
) -> tuple[FloatArray, IntArray]:
    n, m, C = At.shape
    lo = np.broadcast_to(lo, (m, C))
    hi = np.broadcast_to(hi, (m, C))
    mid = 0.5 * (lo + hi)
    T_out = np.empty((m, C))
    status_out = np.full(C, SOLVE_INFEASIBLE, dtype=np.int8)
    free = np.ones((m, C), dtype=bool)
    T_fix = np.zeros((m, C))
    idx = np.arange(C)
    tol = 1e-9 * (1.0 + np.abs(hi).max(axis=0))
    floors = _RankFloor(lo, hi)
    for _ in range(m - n + 1):
        A_k = _take(At, idx)
        fr = _take(free, idx)
        frf = fr.astype(np.float64)
        Tf = _take(T_fix, idx)
        mid_k, lo_k, hi_k = _take(mid, idx), _take(lo, idx), _take(hi, idx)
        Af = A_k * frf
        f = _Factor(Af, floors.sub(idx))
        T = np.where(fr, f.closest(Af, _take(w, idx) - _apply(A_k, Tf), mid_k), Tf)
        T_out[:, idx] = T
        v_lo = lo_k - T
        v_hi = T - hi_k
        v = np.where(fr, np.maximum(v_lo, v_hi), -np.inf)
        worst = np.argmax(v, axis=0)
        ar = np.arange(idx.size)
        vmax = v[worst, ar]
        rank_bad = ~f.ok
        done = (vmax <= tol[idx]) & ~rank_bad
        status_out[idx[done]] = SOLVE_OK
        status_out[idx[rank_bad]] = SOLVE_RANK_DEFICIENT
        n_free = fr.sum(axis=0)
        give_up = ~done & ~rank_bad & (n_free - 1 < n)
        status_out[idx[give_up]] = SOLVE_GAVE_UP
        go = ~done & ~rank_bad & ~give_up
        if not go.any():
            break
        g, j = idx[go], worst[go]
        T_fix[j, g] = np.where(v_lo[j, ar[go]] > v_hi[j, ar[go]], lo[j, g], hi[j, g])
        free[j, g] = False
        idx = g
    return T_out, status_out


def improved_closed_form(
    A: ArrayLike, w: ArrayLike, t_min_N: ArrayLike, t_max_N: ArrayLike
) -> TensionResult:
    """Pott's improved closed form (2014), each cable with its own limits and its own ``T_mid``.

    Closed form; while a free cable violates its limits: clamp the worst violator (largest
    violation in N) at the limit it violates, move its force to the wrench, re-solve the closed form
    for the free cables.  ``status``: OK, GAVE_UP (fewer than n free cables would remain) or
    RANK_DEFICIENT (the reduced structure matrix is below :func:`rank_floor`).  Each closed form
    is solved from the SVD where its matrix is ill-conditioned, as in :func:`closed_form`.
    """
    A_, w_, lo, hi = check_problem(A, w, t_min_N, t_max_N)
    return _Chunked(A_, w_, lo, hi).run(
        _improved_kernel,
        (),
        "min |T - T_mid|_2 (approximate: clamp worst violator, re-solve)",
        "improved-closed-form",
    )


# ---------------------------------------------------------------------------------------------
# Exact min |T - T_ref|_2 for m - n <= 2 (null-space polygon)


def _null_space(f: _Factor, r: int) -> list[FloatArray]:
    """r orthonormal null-space vectors of A, each (m, C), from the orthonormal rows B.

    Column j of the projector ``P = I - B^T B`` is the null-space part of ``e_j``; the column
    with the largest norm (``P_jj``, and ``sum_j P_jj = r``) is taken, then deflated.
    """
    B = f.orthonormal_rows()
    m, C = B.shape[1:]
    ar = np.arange(C)
    diag = 1.0 - np.einsum("imc,imc->mc", B, B)
    out: list[FloatArray] = []
    for _ in range(r):
        j = np.argmax(diag, axis=0)
        v = -np.einsum("imc,ic->mc", B, B[:, j, ar])
        v[j, ar] += 1.0
        for u in out:  # deflate: remove the component along the vectors already taken
            v -= u * np.einsum("mc,mc->c", u, v)
        v /= np.sqrt(np.einsum("mc,mc->c", v, v))
        diag = diag - v * v
        out.append(v)
    return out


def _polygon(
    n1: FloatArray, n2: FloatArray, lo_: FloatArray, hi_: FloatArray, tol: FloatArray
) -> tuple[FloatArray, FloatArray, BoolArray]:
    """Closest point ``lam`` (2 x (K,)) to the origin of ``{lam: lo_ <= n1 lam1 + n2 lam2 <= hi_}``.

    n1, n2, lo_, hi_: (m, K); tol (K,): the constraints are relaxed by tol when intersected.  The
    origin is assumed infeasible.  By the KKT conditions (``lam* = -sum mu_k g_k`` with
    ``|lam*|^2 = -sum mu_k h_k > 0`` for constraints ``g_k . lam <= h_k``) the optimum lies on the
    line of a constraint the origin violates; on each such line the foot of the origin is clipped
    into the line's feasible interval (the line intersected with the other 2m - 1 half-planes; the
    limits' own interval where it is not empty, else the relaxed one).  The candidate that
    satisfies the KKT conditions wins, lines that meet the unrelaxed polygon first; the least norm
    decides only among those (see :func:`_polygon_lines` for why it cannot decide alone).  Poses
    are bucketed by their number of violated constraints, so most poses check one or two lines.
    Returns lam1, lam2 (K,) and found (K,) (False: the polygon is empty).
    """
    m, K = n1.shape
    q = n1 * n1 + n2 * n2  # |n_i|^2, (m, K)
    good = q > _NULL_TOL
    # lines 0..m-1: n_i . lam = lo_i (violated at 0 if lo_i > 0); m..2m-1: = hi_i (if hi_i < 0)
    V = np.concatenate([(lo_ > tol) & good, (hi_ < -tol) & good])
    cnt = V.sum(axis=0)
    out = (np.zeros(K), np.zeros(K), np.zeros(K, dtype=bool))
    lower = lo_ - tol
    upper = hi_ + tol
    width = upper - lower
    prev = 0
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        for kb in (2, 4, 2 * m):
            sel = np.flatnonzero((cnt > prev) & (cnt <= kb))
            prev = kb
            if sel.size:
                _polygon_lines(n1, n2, lo_, hi_, q, V, lower, width, tol, kb, sel, out)
    return out


def _polygon_lines(
    n1: FloatArray,
    n2: FloatArray,
    lo_: FloatArray,
    hi_: FloatArray,
    q: FloatArray,
    V: BoolArray,
    lower: FloatArray,
    width: FloatArray,
    tol: FloatArray,
    kb: int,
    sel: NDArray[np.intp],
    out: tuple[FloatArray, FloatArray, BoolArray],
) -> None:
    """:func:`_polygon` for the poses ``sel``, which violate at most ``kb`` constraints at 0."""
    m = n1.shape[0]
    Ks = sel.size
    ar = np.arange(Ks)[None, :]
    Vs = _take(V, sel)
    if kb < 2 * m:  # the first kb violated lines of each pose
        Vc = Vs.copy()
        picks = []
        for _ in range(kb):
            j = np.argmax(Vc, axis=0)
            picks.append(j)
            Vc[j, ar[0]] = False
        lines = np.stack(picks)  # (kb, Ks)
    else:
        lines = np.broadcast_to(np.arange(2 * m)[:, None], (2 * m, Ks))
    valid = Vs[lines, ar]
    i = lines % m
    n1s, n2s, los, his = _take(n1, sel), _take(n2, sel), _take(lo_, sel), _take(hi_, sel)
    n1i, n2i, qi = n1s[i, ar], n2s[i, ar], _take(q, sel)[i, ar]
    c = np.where(lines < m, los[i, ar], his[i, ar])
    qi = np.where(valid, qi, 1.0)
    t = c / qi  # foot of the origin on the line is t n_i; points t n_i + s (-n2_i, n1_i)
    # constraint l along line i: lower_l <= n_l . (t n_i) + s (n_i x n_l) <= lower_l + width_l
    dot = n1i[:, None] * n1s[None]  # n_l . n_i, (kb, m, Ks)
    dot += n2i[:, None] * n2s[None]
    a = _take(lower, sel)[None] - t[:, None] * dot
    e = n1i[:, None] * n2s[None]
    e -= n2i[:, None] * n1s[None]
    b = a + _take(width, sel)[None]
    # A parallel constraint (e = 0, e.g. the line's own cable) gives -inf..inf if it holds
    # (a < 0 < b), an empty interval if not, NaN (ignored by fmin/fmax) if it holds with equality.
    a /= e
    b /= e
    lo_s = np.fmin(a, b)
    hi_s = np.fmax(a, b, out=b)
    slo = np.fmax.reduce(lo_s, axis=1)  # (kb, Ks)
    shi = np.fmin.reduce(hi_s, axis=1)
    ok = valid & (slo <= shi)
    # the relaxed interval decides whether the line meets the polygon; the point is clipped into
    # the interval of the limits themselves where that is not empty (the relaxation would move a
    # vertex by tol / sin(angle), 2e-7 N where narrow ranges cross at a shallow angle)
    tol_e = _take(tol, sel) / np.abs(e)
    lo_0 = lo_s + tol_e
    hi_0 = hi_s - tol_e
    slo0 = np.fmax.reduce(lo_0, axis=1)
    shi0 = np.fmin.reduce(hi_0, axis=1)
    unrelaxed: BoolArray = np.less_equal(slo0, shi0)
    slo = _select(unrelaxed, slo0, slo)
    shi = _select(unrelaxed, shi0, shi)
    lo_s = _select(unrelaxed[:, None], lo_0, lo_s)
    hi_s = _select(unrelaxed[:, None], hi_0, hi_s)
    s = np.minimum(np.maximum(0.0, slo), shi)
    ok &= np.abs(s) < _BIG
    norm2 = np.where(ok, (c * c + s * s * qi * qi) / qi, np.inf)  # |t n_i|^2 + s^2 |n_i|^2
    # The least norm alone is not a safe choice: a candidate on line j clipped by a constraint
    # relaxed by tol can beat the optimum by ~|lam| tol in norm^2 (or by the rounding of norm^2,
    # ~eps |lam|^2), and since |x|^2 >= |x*|^2 + |x - x*|^2 on the polygon, the wrong point can be
    # ~sqrt(|lam| tol) away -- 1e-5 N when a range narrower than that puts two candidates close.
    # So the candidate that satisfies the KKT conditions wins: the foot itself (s = 0: the
    # polygon lies in the line's half-plane, whose closest point it is), or a vertex with the one
    # cable l bounding the interval where the multiplier of line i, sigma_i (t - s rho_l),
    # rho_l = (n_l . n_i) / (n_l x n_i), is >= 0 (as in :func:`_polygon_one_line`).  The least
    # norm decides only among certified candidates, or when none is (ties of two bounds).
    at_hi = np.less(s, 0.0)[:, None]
    bound = np.where(at_hi, hi_s == shi[:, None], lo_s == slo[:, None])
    one = bound.sum(axis=1) == 1
    rho_b = np.where(bound, dot / e, -np.inf).max(axis=1)
    mu = np.where(lines < m, 1.0, -1.0) * (t - s * rho_b)
    cert = ok & ((s == 0.0) | (one & (mu >= 0.0)))
    # lines that meet the polygon of the limits themselves come first: where it is not empty, the
    # optimum is on one of them, and a vertex of the relaxed polygon can be far from it
    if_exact = ok & unrelaxed
    first = np.where(if_exact.any(axis=0), if_exact, ok)
    pick = np.where((cert & first).any(axis=0), cert & first, first)
    best = np.argmin(np.where(pick, norm2, np.inf), axis=0)
    ab = np.arange(Ks)
    f = np.isfinite(norm2[best, ab])
    tb, sb = t[best, ab], np.where(f, s[best, ab], 0.0)
    n1b, n2b = n1i[best, ab], n2i[best, ab]
    lam1, lam2, found = out
    lam1[sel] = tb * n1b - sb * n2b
    lam2[sel] = tb * n2b + sb * n1b
    found[sel] = f


def _select(cond: BoolArray, a: FloatArray, b: FloatArray) -> FloatArray:
    """``np.where(cond, a, b)`` (typed: mypy resolves some calls to the one-argument form)."""
    out: FloatArray = np.where(cond, a, b)
    return out


def _interval(
    n1: FloatArray, lo_: FloatArray, hi_: FloatArray, tol: FloatArray
) -> tuple[FloatArray, BoolArray]:
    """Closest point to 0 of ``{lam: lo_ <= n1 lam <= hi_}`` (1-D null space); (K,), found."""
    d = np.where(n1 >= 0, np.maximum(n1, _TINY), np.minimum(n1, -_TINY))
    a, b = (lo_ - tol) / d, (hi_ + tol) / d
    slo = np.minimum(a, b).max(axis=0)
    shi = np.maximum(a, b).min(axis=0)
    s = np.minimum(np.maximum(0.0, slo), shi)
    found = (slo <= shi) & (np.abs(s) < _BIG)
    return np.where(found, s, 0.0), found


def _exact_kernel(
    At: FloatArray,
    w: FloatArray,
    lo: FloatArray,
    hi: FloatArray,
    ref: FloatArray,
) -> tuple[FloatArray, IntArray]:
    n, m, C = At.shape
    ref = np.broadcast_to(ref, (m, C))
    f = _Factor(At, _RankFloor(lo, hi, ref))
    svd = f.ok & (f.floor < SVD_BELOW)  # ill-conditioned, not rank deficient: from the SVD
    T, status, low, at = _exact_solve(f, At, w, lo, hi, ref, svd)
    if m == n:
        return T, status
    # At a limit the normal equations' error is ~ eps |T| / (sigma_min sigma_F): the poses whose
    # sigma_F is not certified above SVD_BELOW are solved again from the SVD
    redo = np.flatnonzero((status == SOLVE_OK) & ~svd & (low < SVD_BELOW))
    if redo.size:
        a_, w_, lo_, hi_, ref_ = (_take(x, redo) for x in (At, w, lo, hi, ref))
        every = np.ones(redo.size, dtype=bool)
        T2, st2, low2, at2 = _exact_solve(f.subset(redo), a_, w_, lo_, hi_, ref_, every)
        T[:, redo], status[redo], low[redo], at[:, redo] = T2, st2, low2, at2
    # the rank test on the reduced matrix at the answer (RANK_TOL)
    check = np.flatnonzero((status == SOLVE_OK) & (low < max(f.floors.cap, _TRUST_BELOW)))
    if check.size:
        fl = f.floors.at(check)
        near = low[check] < np.maximum(fl, _TRUST_BELOW)
        check, fl = check[near], fl[near]
        bad = _sigma_free(f.As, at, check) < fl
        status[check[bad]] = SOLVE_RANK_DEFICIENT
    return T, status


def _exact_solve(
    f: _Factor,
    At: FloatArray,
    w: FloatArray,
    lo: FloatArray,
    hi: FloatArray,
    ref: FloatArray,
    svd: BoolArray,
) -> tuple[FloatArray, IntArray, FloatArray, BoolArray]:
    """T (m, C), status (C,), a lower bound (C,) of the answer's sigma_F (sigma_min(A') where no
    limit is reached) and the cables at a limit (m, C); the poses ``svd`` from the SVD of A'."""
    n, m, C = At.shape
    r = m - n
    Tp = ref + f.pinv(w - _apply(At, ref))
    low = f.floor.copy()
    at = np.zeros((m, C), dtype=bool)
    weak = np.flatnonzero(svd)
    n_svd: FloatArray | None = None
    if weak.size:
        Tp[:, weak], n_svd, low[weak] = _svd_solve(
            f, weak, _take(w, weak), _take(At, weak), _take(ref, weak)
        )
    lo_ = lo - Tp
    hi_ = hi - Tp
    tol = _REL_TOL * (1.0 + np.abs(hi).max(axis=0))
    tol = np.broadcast_to(tol, (C,))
    need = ((lo_ > tol) | (hi_ < -tol)).any(axis=0) & f.ok
    status = np.where(f.ok, SOLVE_OK, SOLVE_RANK_DEFICIENT).astype(np.int8)
    T = Tp
    if r == 0:
        status[need] = SOLVE_INFEASIBLE
        return T, status, low, at
    idx = np.flatnonzero(need)
    if idx.size == 0:
        return T, status, low, at
    if idx.size < C:  # only the poses whose T_p violates a limit need the null space
        sub = f.subset(idx)
    else:
        sub = f
    N = _null_space(sub, r)
    if n_svd is not None:
        where = np.full(C, -1)
        where[weak] = np.arange(weak.size)
        pos = where[idx]
        use = np.flatnonzero(pos >= 0)
        for j in range(r):
            N[j][:, use] = n_svd[j][:, pos[use]]
    lo_k, hi_k, tol_k = _take(lo_, idx), _take(hi_, idx), tol[idx]
    if r == 1:
        lam, found = _interval(N[0], lo_k, hi_k, tol_k)
        T[:, idx] += N[0] * lam
    else:
        lam1, lam2, found = _polygon(N[0], N[1], lo_k, hi_k, tol_k)
        lam1[~found] = 0.0  # infeasible: T_p (balances w, violates a limit)
        lam2[~found] = 0.0
        T[:, idx] += N[0] * lam1 + N[1] * lam2
    status[idx[~found]] = SOLVE_INFEASIBLE
    at_k = _at_limit(_take(T, idx), _take(lo, idx), _take(hi, idx))
    at[:, idx] = at_k
    low[idx] = _free_sigma_low(low[idx], N, at_k)
    return T, status, low, at


def _at_limit(T: FloatArray, lo: FloatArray, hi: FloatArray) -> BoolArray:
    """The cables (m, K) the answer T puts at a limit: the columns the rank test on the reduced
    matrix takes out.  The polygon puts a cable on its limit to the rounding or the relaxation
    (``_REL_TOL (1 + max t_max)``); 10 times that, so that a cable merely near its limit (the
    answer is then decided by the objective, not by that limit) stays in."""
    delta = 10.0 * _REL_TOL * (1.0 + np.abs(hi).max(axis=0))
    return (T - lo <= delta) | (hi - T <= delta)


def _free_sigma_low(sigma_R: FloatArray, N: list[FloatArray], at: BoolArray) -> FloatArray:
    """Lower bound (K,) of ``sigma_F``, the smallest singular value of ``A'_F`` (``A'`` without the
    columns ``at`` (m, K)), from a lower bound ``sigma_R`` (K,) of ``sigma_min(A')`` and the
    orthonormal null-space basis N (r vectors (m, K)).

    With ``B`` orthonormal rows spanning the rows of ``A' = R B`` and ``G = N[at]`` (|S| x r),
    ``C = [A'; E_S]`` times the orthogonal ``[B; N^T]^T`` is ``M = [R 0; X G]`` (``|X| <= 1``), and
    ``Z = [R^-1 0; -G^+ X R^-1  G^+]`` inverts it (from the right if |S| < r, the left otherwise),
    so ``sigma_min(C) >= 1/|Z| >= sigma_R sigma_G / (1 + sigma_R + sigma_G)`` with ``sigma_G`` the
    smallest of the min(|S|, r) singular values of G; and ``sigma_F >= sigma_min(C)`` (a vector
    of C's row space with the components on S removed is one of A'_F's, and vice versa for
    columns).  No cable at a limit: ``sigma_F = sigma_min(A')``.
    """
    k = at.sum(axis=0)
    n1a = N[0] * at
    a = np.einsum("mk,mk->k", n1a, N[0])
    if len(N) == 1:
        g2 = a
    else:
        n2 = N[1]
        b = np.einsum("mk,mk->k", n1a, n2)
        c = np.einsum("mk,mk->k", n2 * at, n2)
        big = 0.5 * (a + c) + np.sqrt(0.25 * (a - c) ** 2 + b * b)
        small = np.divide(a * c - b * b, big, out=np.zeros_like(big), where=big > 0)
        g2 = np.where(k >= 2, small, a + c)  # lambda_min(G^T G), or |g|^2 for one cable
    sigma_G = np.sqrt(np.maximum(g2, 0.0))
    return np.where(k > 0, sigma_R * sigma_G / (1.0 + sigma_R + sigma_G), sigma_R)


def _sigma_free(As: FloatArray, at: BoolArray, idx: NDArray[np.intp]) -> FloatArray:
    """``sigma_F`` (K,) of the poses idx: the smallest of the min(n, |F|) singular values of the
    unit-row ``As`` (n, m, C) with the columns ``at`` (m, C) zeroed (LAPACK SVD); inf if |F| = 0."""
    n = As.shape[0]
    keep = ~_take(at, idx)
    M = _take(As, idx) * keep[None]
    sv = np.linalg.svd(np.moveaxis(M, -1, 0), compute_uv=False)  # (K, n), descending
    k = np.minimum(keep.sum(axis=0), n)
    out = np.full(idx.size, np.inf)
    has = k > 0
    out[has] = sv[np.flatnonzero(has), k[has] - 1]
    return out


def _svd_solve(
    f: _Factor, k: NDArray[np.intp], w: FloatArray, At: FloatArray, ref: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``T_p = T_ref + A^+ (w - A T_ref)`` (m, K), an orthonormal null-space basis (r, m, K) and
    ``sigma_min(A')`` (K,) of the poses ``k`` of the factor's chunk from the SVD ``A' = U S V^T``
    (w, At, ref: those poses).  Error ~ eps |T| / sigma_min, against eps |T| / sigma_min^2 for the
    normal equations."""
    n = f.n
    As = np.moveaxis(_take(f.As, k), -1, 0)  # (K, n, m)
    U, sv, Vt = np.linalg.svd(As, full_matrices=True)
    rs = _take(f.rs, k)
    Tp = ref.copy()
    for _ in range(2):  # the solve and one step of iterative refinement
        rhs = np.einsum("kji,jk->ik", U, rs * (w - _apply(At, Tp))) / sv.T
        Tp += np.einsum("kim,ik->mk", Vt[:, :n], rhs)
    return Tp, np.moveaxis(Vt[:, n:], 0, -1), sv[:, -1]


# Fast path for m = n + 2 (the paper's rigs), used by :func:`exact`.  Per chunk: Gaussian
# elimination of [A' | w'] (A': A with unit-norm rows) in one pivot order for the whole batch, a
# per-pose check that this order is stable for the pose, the null-space basis and T_p from the
# reduced form; for the poses whose T_p violates a limit, the polygon on ONE line (the most
# violated one) with a certificate: the KKT conditions at the point found there (optimum) or three
# half-planes without a common point (infeasible).  Poses that fail a check or a certificate go
# through the general kernel above (same answers, slower).  Everything in the chunk is in the
# pivot order (rows p, cables q) until the tensions are written out.

_LU_RATIO = 0.25
"""Fast path: each elimination pivot must be >= this times every entry below it (bounded growth, as
with partial pivoting) and >= :data:`_LU_PIVOT`, else the pose takes the general kernel."""
_LU_PIVOT = 1e-3
_DET_MIN = 1e-4
"""Fast path: a pose is taken only if ``|det [A'; N^T]| >= _DET_MIN n^((n-1)/2)``, which keeps
the near-singular poses for the general kernel's SVD.  For the m x m matrix ``[A'; N^T]`` (squared
Frobenius norm m, singular values those of A' and 1) Hong and Pan's bound gives
``sigma_min(A') >= |det| ((m-1)/m)^((m-1)/2)`` (:func:`_hong_pan`), 5.5e-3 at that limit."""
_ORDER_SAMPLES = 32  # poses sampled to choose the pivot order


def _pivot_order(a: FloatArray) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Row and column order for the elimination of the sample of poses a (S, n, m), m = n + 2.

    Columns: the n basic columns are those whose n x n block of ``A'`` has the largest smallest
    ``|det|`` over the sample (the best block for one pose can be singular a few mm away), then
    the two free ones.  Rows: partial pivoting on the sample's first pose.
    """
    S, n, m = a.shape
    with np.errstate(all="ignore"):
        a = a / np.linalg.norm(a, axis=-1, keepdims=True)
        subsets = [[j for j in range(m) if j not in f] for f in combinations(range(m), m - n)]
        dets = np.abs(np.linalg.det(np.moveaxis(a[:, :, subsets], 2, 0)))  # (subsets, S)
        basic = subsets[int(np.argmax(np.nan_to_num(dets).min(axis=1)))]
        q = np.array(basic + [j for j in range(m) if j not in basic])
        M = np.nan_to_num(a[0][:, q])
    p = np.arange(n)
    for k in range(n):
        i = k + int(np.argmax(np.abs(M[k:, k])))
        M[[k, i]], p[[k, i]] = M[[i, k]], p[[i, k]]
        if M[k, k] != 0.0:
            M[k + 1 :] -= np.outer(M[k + 1 :, k] / M[k, k], M[k])
    return p, q


def _cols(x: FloatArray, s: int, e: int, order: NDArray[np.intp]) -> FloatArray:
    """Rows s:e of x (N, k), columns in ``order``, as a (k, e - s) array (or (k, 1) if constant)."""
    if x.strides[0] == 0:
        return np.ascontiguousarray(x[0, order][:, None])
    return np.ascontiguousarray(x[s:e][:, order].T)


def _exact2(
    A: FloatArray, w: FloatArray, lo: FloatArray, hi: FloatArray, ref: FloatArray, objective: str
) -> TensionResult:
    """:func:`exact` for m = n + 2: the fast path chunk by chunk, then the general kernel once for
    the poses the fast path left."""
    lead = A.shape[:-2]
    n, m = A.shape[-2:]
    A, w, lo, hi, ref = _flat(A, 2), _flat(w, 1), _flat(lo, 1), _flat(hi, 1), _flat(ref, 1)
    N = A.shape[0]
    T = np.empty((N, m))
    feas = np.empty(N, dtype=bool)
    res = np.empty(N)
    viol = np.empty(N)
    status = np.empty(N, dtype=np.int8)
    out = (T, feas, res, viol, status)
    if N:  # an empty batch has nothing to order or solve
        order = _pivot_order(A[np.linspace(0, N - 1, min(N, _ORDER_SAMPLES)).astype(np.intp)])
        deferred = []
        for s in range(0, N, CHUNK):
            e = min(N, s + CHUNK)
            bad, undecided = _exact2_chunk(A, w, lo, hi, ref, s, e, order, out)
            deferred += [s + bad, s + undecided]
            if 8 * bad.size > e - s:  # the order does not suit this part of the batch: re-choose
                pick = np.linspace(0, bad.size - 1, min(bad.size, _ORDER_SAMPLES)).astype(np.intp)
                order = _pivot_order(A[s + bad[pick]])
        d = np.concatenate(deferred)
        if d.size:
            _check_finite_A(A[d])
            sub = _Chunked(A[d], w[d], lo[d], hi[d]).run(
                _exact_kernel, (ref[d],), objective, "exact"
            )
            T[d], feas[d], res[d], viol[d] = (
                sub.tensions_N,
                sub.feasible,
                sub.residual_N,
                sub.max_violation_N,
            )
            assert sub.status is not None
            status[d] = sub.status
    return TensionResult(
        T.reshape(lead + (m,)),
        feas.reshape(lead),
        res.reshape(lead),
        viol.reshape(lead),
        objective,
        "exact",
        status.reshape(lead),
    )


def _exact2_chunk(
    A: FloatArray,
    w: FloatArray,
    lo: FloatArray,
    hi: FloatArray,
    ref: FloatArray,
    s: int,
    e: int,
    order: tuple[NDArray[np.intp], NDArray[np.intp]],
    out: tuple[FloatArray, BoolArray, FloatArray, FloatArray, IntArray],
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Solve the poses s:e (flat inputs) into ``out`` (tensions, feasible, residual, violation,
    status).  Returns the chunk positions that do not suit the pivot order and those whose polygon
    was not certified on its most violated line: the caller solves both again."""
    n, m = A.shape[-2:]
    C = e - s
    p, q = order
    J = p[:, None] * m + q
    Ap = np.ascontiguousarray(A[s:e].reshape(C, n * m)[:, J.ravel()].T).reshape(n, m, C)
    wp, lo_q, hi_q = _cols(w, s, e, p), _cols(lo, s, e, q), _cols(hi, s, e, q)
    tol = np.broadcast_to(_REL_TOL * (1.0 + np.abs(hi_q).max(axis=0)), (C,))
    S = np.empty((4, m, C))  # n1, n2, lo - T_p, hi - T_p
    status = np.zeros(C, dtype=np.int8)
    ref_q = _cols(ref, s, e, q)
    with np.errstate(all="ignore"):
        Tp, ok, det = _reduce(Ap, wp, ref_q, S[0], S[1])
        lo_, hi_ = S[2], S[3]
        np.subtract(lo_q, Tp, out=lo_)
        np.subtract(hi_q, Tp, out=hi_)
        need = (lo_ > tol).any(axis=0)
        need |= (hi_ < -tol).any(axis=0)
        need &= ok
        idx = np.flatnonzero(need)
        undecided = idx
        if idx.size:
            Sk = np.take(S, idx, axis=-1)
            lam1, lam2, state = _polygon_one_line(Sk[0], Sk[1], Sk[2], Sk[3], tol[idx])
            undecided = idx[state == 2]
            status[idx[state == 1]] = SOLVE_INFEASIBLE
            L = np.zeros((2, C))
            L[0, idx] = lam1
            L[1, idx] = lam2
            S[0] *= L[0]
            S[1] *= L[1]
            Tp += S[0]
            Tp += S[1]
        # keep only the answers whose conditioning is certified well clear of the rank floor:
        # sigma_min(A') (Hong-Pan, from det) or, at a limit, sigma_F (:func:`_free_sigma_low`)
        low = _hong_pan(det, m)
        if idx.size:
            solved = np.flatnonzero(state == 0)
            k = idx[solved]
            at = _at_limit(np.take(Tp, k, axis=1), _take_cols(lo_q, k), _take_cols(hi_q, k))
            N = [Sk[0][:, solved], Sk[1][:, solved]]
            low[k] = _free_sigma_low(low[k], N, at)
        weak = np.flatnonzero(ok & ~(low >= max(_FAST_MARGIN * _FLOOR_CAP, _TRUST_BELOW)))
        if weak.size:
            floor = _RankFloor(lo_q, hi_q, ref_q).at(weak)
            weak = weak[~(low[weak] >= np.maximum(_FAST_MARGIN * floor, _TRUST_BELOW))]
    # the contract's summary, in the pivot order (row order does not change |A T - w|)
    r = np.einsum("imc,mc->ic", Ap, Tp)
    r -= wp
    res = np.sqrt(np.einsum("ic,ic->c", r, r))
    viol = np.subtract(lo_q, Tp, out=S[2])
    np.maximum(viol, np.subtract(Tp, hi_q, out=S[3]), out=viol)
    vmax = viol.max(axis=0)
    np.maximum(vmax, 0.0, out=vmax)
    ftol = FEASIBILITY_TOL_N * (1.0 + np.abs(hi_q).max(axis=0))
    feas = (res <= ftol) & (vmax <= ftol) & (status == SOLVE_OK)
    status[~feas & (status == SOLVE_OK)] = SOLVE_INFEASIBLE
    T_out, feas_out, res_out, viol_out, status_out = out
    T_out[s:e] = Tp.take(np.argsort(q), axis=0).T
    feas_out[s:e], res_out[s:e], viol_out[s:e], status_out[s:e] = feas, res, vmax, status
    redo = np.zeros(C, dtype=bool)
    redo[undecided] = True
    redo[weak] = True
    return np.flatnonzero(~ok), np.flatnonzero(redo)


def _reduce(
    Ap: FloatArray, wp: FloatArray, ref_q: FloatArray, n1: FloatArray, n2: FloatArray
) -> tuple[FloatArray, BoolArray, FloatArray]:
    """T_p (m, C), written n1, n2 (m, C; orthonormal null-space basis), ok (C,) and
    ``|det [A'; N^T]|`` (C,), in pivot order.

    Gaussian elimination of ``[A' | w']`` without further pivoting, then ``[x0 x1 xw] =
    A1'^-1 [free columns | w']`` by back substitution: the null space is spanned by ``[-x0; 1; 0]``
    and ``[-x1; 0; 1]``, ``T0 = [xw; 0; 0]`` is a particular solution and
    ``T_p = T0 - N N^T (T0 - T_ref)``.  ``ok`` is False where a pivot check fails.
    """
    n, m, C = Ap.shape
    rs = np.einsum("imc,imc->ic", Ap, Ap)
    np.sqrt(rs, out=rs)
    np.divide(1.0, rs, out=rs)
    M = np.empty((n, m + 1, C))
    np.multiply(Ap, rs[:, None, :], out=M[:, :m])
    np.multiply(wp, rs, out=M[:, m])
    ok = np.ones(C, dtype=bool)
    E = np.empty((n - 1, m, C))
    for k in range(n - 1):
        mult = M[k + 1 :, k] / M[k, k]  # |multipliers| <= 1 / _LU_RATIO
        ok &= np.abs(mult).max(axis=0) <= 1.0 / _LU_RATIO
        t = E[: n - 1 - k, : m - k]
        np.multiply(mult[:, None, :], M[k, None, k + 1 :], out=t)
        M[k + 1 :, k + 1 :] -= t
    diag = M[np.arange(n), np.arange(n)]
    piv = np.abs(diag)
    ok &= piv.min(axis=0) >= _LU_PIVOT
    det = np.prod(piv, axis=0)
    inv = np.divide(1.0, diag, out=diag)
    X = np.empty((3, n, C))  # back substitution: the two free columns and w'
    np.multiply(M[n - 1, n:], inv[n - 1], out=X[:, n - 1])
    for k in range(n - 2, -1, -1):
        acc = np.einsum("jc,rjc->rc", M[k, k + 1 : n], X[:, k + 1 :])
        np.subtract(M[k, n:], acc, out=acc)
        np.multiply(acc, inv[k], out=X[:, k])
    x0, x1, xw = X
    g11 = np.einsum("kc,kc->c", x0, x0)
    g11 += 1.0
    g12 = np.einsum("kc,kc->c", x0, x1)
    g22 = np.einsum("kc,kc->c", x1, x1)
    g22 += 1.0
    beta = g12 / g11
    gram = g22 - g12 * beta
    det *= np.sqrt(g11 * gram)  # |det [A'; N^T]| = |det A1'| sqrt(det(I + F^T F))
    ok &= det >= _DET_MIN * n ** ((n - 1) / 2)
    a1 = 1.0 / np.sqrt(g11)
    a2 = 1.0 / np.sqrt(gram)
    np.multiply(x0, -a1, out=n1[:n])  # [-x0; 1; 0] / sqrt(g11)
    n1[n] = a1
    n1[n + 1] = 0.0
    np.multiply(x0, beta, out=n2[:n])  # ([-x1; 0; 1] - beta [-x0; 1; 0]) / sqrt(gram)
    n2[:n] -= x1
    n2[:n] *= a2
    np.multiply(beta, -a2, out=n2[n])
    n2[n + 1] = a2
    Tp = np.empty((m, C))  # T0 - T_ref, then T_p
    np.subtract(xw, ref_q[:n], out=Tp[:n])
    np.negative(ref_q[n:], out=Tp[n:])
    c1 = np.einsum("mc,mc->c", n1, Tp)
    c2 = np.einsum("mc,mc->c", n2, Tp)
    tmp = n1 * c1
    Tp -= tmp
    np.multiply(n2, c2, out=tmp)
    Tp -= tmp
    Tp += ref_q
    return Tp, ok, det


def _hong_pan(det: FloatArray, m: int) -> FloatArray:
    """Lower bound of ``sigma_min(A')`` from ``|det [A'; N^T]|`` (m x m, squared Frobenius norm m):
    ``sigma_min(M) >= |det M| ((k-1)/|M|_F^2)^((k-1)/2)`` (Hong and Pan 1992) for k = m, and the
    singular values of ``[A'; N^T]`` are those of A' and 1."""
    return det * ((m - 1) / m) ** ((m - 1) / 2)


def _take_cols(x: FloatArray, k: NDArray[np.intp]) -> FloatArray:
    """Columns k of x (m, C), or x itself if it is constant over the batch (m, 1)."""
    return x if x.shape[-1] == 1 else np.take(x, k, axis=-1)


def _polygon_one_line(
    n1: FloatArray, n2: FloatArray, lo_: FloatArray, hi_: FloatArray, tol: FloatArray
) -> tuple[FloatArray, FloatArray, IntArray]:
    """:func:`_polygon` on one violated line per pose (the most violated one), certified.

    Line i (``n_i . lam = c_i``, violated at 0) is ``x(s) = t n_i + s d_i`` with ``t = c_i/|n_i|^2``,
    ``d_i = (-n_i2, n_i1)``; the other constraints (relaxed by tol) allow ``[slo, shi]`` there, as
    in :func:`_polygon_lines`.  Shifting the line by ``dc`` into the half-plane ``H_i`` moves the
    bounds of cable l by ``-rho_l dc / |n_i|^2``, ``rho_l = (n_l . n_i) / (n_l . d_i)``.

    - Interval not empty, ``s`` its point closest to 0: optimal if ``s = 0`` (the foot of 0 is
      feasible: no feasible point is closer than any violated line), or if the KKT conditions hold
      at the vertex with the bounding cable b: along b's line into ``H_i`` the objective
      ``c^2/|n_i|^2 + s(c)^2 |n_i|^2`` must not decrease, i.e. ``sigma_i (t - s rho_b) >= 0``
      (``sigma_i`` = +1 for a lower limit, -1 for an upper one).
    - Interval empty (``slo`` from cable l1 > ``shi`` from cable l2): if the gap does not shrink
      into ``H_i`` (``sigma_i (rho_l2 - rho_l1) >= 0``) and survives the relaxation of line i by
      tol, the half-planes of l1, l2 and i have no common point: the polygon is empty.

    A bound attained by two cables at once is left uncertified.  Returns lam1, lam2 (K,) and
    state (K,): 0 optimum found, 1 polygon empty, 2 not certified.
    """
    m, K = n1.shape
    low = np.int64((1 << max(1, (m - 1).bit_length())) - 1)
    # the most violated limit (in N) picks line i: integer max of the violation's float bits
    # (order-preserving for values >= 0) with the row index in the lowest bits
    v = np.negative(hi_)
    np.maximum(v, lo_, out=v)
    np.maximum(v, 0.0, out=v)
    key = v.view(np.int64)
    key &= ~low
    key |= np.arange(m, dtype=np.int64)[:, None]
    fi = np.bitwise_and(key.max(axis=0), low)
    fi *= K
    fi += np.arange(K)
    n1i, n2i = n1.ravel().take(fi), n2.ravel().take(fi)
    loi, hii = lo_.ravel().take(fi), hi_.ravel().take(fi)
    ci = np.where(loi > tol, loi, hii)
    qi = n1i * n1i + n2i * n2i
    t = ci / qi
    dot = n1 * n1i
    e = n2 * n1i
    base = np.multiply(n2, n2i, out=v)
    dot += base
    np.multiply(n1, n2i, out=base)
    e -= base
    np.multiply(dot, t, out=base)
    a = lo_ - tol
    a -= base
    a /= e
    b = hi_ + tol
    b -= base
    b /= e
    lo_s = np.fmin(a, b)
    hi_s = np.fmax(a, b, out=b)
    slo = np.fmax.reduce(lo_s, axis=0)
    shi = np.fmin.reduce(hi_s, axis=0)
    rho = np.divide(dot, e, out=dot)
    sel = lo_s == slo
    one1 = sel.sum(axis=0) == 1
    rho1 = np.where(sel, rho, -np.inf).max(axis=0)
    np.equal(hi_s, shi, out=sel)
    one2 = sel.sum(axis=0) == 1
    rho2 = np.where(sel, rho, -np.inf).max(axis=0)
    sig = np.sign(ci)
    fin = np.isfinite(slo) & np.isfinite(shi) & (qi > _NULL_TOL) & (np.abs(ci) > tol)
    s = np.minimum(np.maximum(0.0, slo), shi)
    at_hi = s < 0.0
    kkt = sig * (t - s * np.where(at_hi, rho2, rho1)) >= 0.0
    kkt &= np.where(at_hi, one2, one1)
    opt = fin & (slo <= shi) & ((s == 0.0) | kkt)
    gap = slo - shi
    drho = rho2 - rho1
    empty = fin & one1 & one2 & (sig * drho >= 0.0)
    empty &= gap > tol * np.abs(drho) / qi + 1e-12 * (np.abs(slo) + np.abs(shi))
    state = np.full(K, 2, dtype=np.int8)
    state[empty] = 1
    state[opt] = 0
    x1 = t * n1i - s * n2i
    x2 = t * n2i + s * n1i
    return np.where(opt, x1, 0.0), np.where(opt, x2, 0.0), state


def exact(
    A: ArrayLike,
    w: ArrayLike,
    t_min_N: ArrayLike,
    t_max_N: ArrayLike,
    *,
    t_ref_N: ArrayLike | None = None,
) -> TensionResult:
    """Exact min ``|T - T_ref|_2`` s.t. ``A T = w``, ``t_min <= T <= t_max``, for m - n <= 2.

    ``T_ref`` defaults to ``T_mid = (t_min + t_max)/2``; ``t_ref_N=t_min_N`` gives the penalty
    method's objective.  With ``T_p = T_ref + A^+ (w - A T_ref)`` and an orthonormal null-space
    basis ``N`` (m, m - n), ``T = T_p + N lam`` and ``|T - T_ref|^2 = |T_p - T_ref|^2 + |lam|^2``:
    the answer is the point of the polygon (interval for m = n + 1) ``{lam: limits}`` closest to
    the origin.  ``feasible=False`` with ``status == SOLVE_INFEASIBLE`` certifies that no tensions
    within the limits, relaxed by ``1e-12 (1 + max t_max)`` N, balance ``w``; the tensions are then
    ``T_p``.  For m = n + 2 a fast path (shared pivot order, one certified line of the polygon, see
    docs/tension.md) solves the poses it can and leaves the others to the general kernel.

    Accuracy: within :data:`ACCURACY_N` of the exact optimum of the problem as given (and of
    quadprog), also for limit ranges narrower than that; otherwise ``SOLVE_RANK_DEFICIENT``: the
    pose's ``sigma_min(A')``, or at the answer the smallest singular value of ``A'`` restricted to
    the cables not at a limit, is below :func:`rank_floor` (``t_ref_N`` included in the scale).
    A: (..., n, m); w: (..., n); t_min_N, t_max_N, t_ref_N: (..., m) or (m,), N.
    """
    # A is scanned for NaN/inf by the fast path (a non-finite row fails its pivot checks, and
    # those poses are checked below) or here for the general kernel
    A_, w_, lo, hi = check_problem(A, w, t_min_N, t_max_N, finite_A=False)
    n, m = A_.shape[-2:]
    if m - n > 2:
        raise InputError(f"exact: supports m - n <= 2 redundant cables, got n={n}, m={m}")
    if m - n != 2:
        _check_finite_A(A_)
    ref = _ref_from_options(lo, hi, t_ref_N)
    if ref.shape[:-1] != lo.shape[:-1]:
        lead = np.broadcast_shapes(ref.shape[:-1], lo.shape[:-1])
        A_, w_ = np.broadcast_to(A_, lead + (n, m)), np.broadcast_to(w_, lead + (n,))
        lo, hi = np.broadcast_to(lo, lead + (m,)), np.broadcast_to(hi, lead + (m,))
        ref = np.broadcast_to(ref, lead + (m,))
    objective = "min |T - T_mid|_2" if t_ref_N is None else "min |T - T_ref|_2"
    if m - n == 2:
        return _exact2(A_, w_, lo, hi, ref, objective)
    return _Chunked(A_, w_, lo, hi).run(_exact_kernel, (ref,), objective, "exact")


# ---------------------------------------------------------------------------------------------
# The paper's penalty method


PENALTY_LAMBDAS = tuple(10.0**k for k in range(0, 11))
"""The default lambda schedule of :func:`penalty` (geometric, warm started)."""


_STEPS = 0.5 ** np.arange(12)  # backtracking grid of the penalty method's Newton steps


def _penalty_kernel(
    At: FloatArray,
    w: FloatArray,
    lo: FloatArray,
    hi: FloatArray,
    lambdas: tuple[float, ...] = PENALTY_LAMBDAS,
    newton_iters: int = 30,
) -> tuple[FloatArray, IntArray]:
    n, m, C = At.shape
    rn = np.sqrt(np.einsum("imc,imc->ic", At, At))
    rs = np.divide(1.0, rn, out=np.zeros_like(rn), where=rn > 0)
    As = np.ascontiguousarray((At * rs[:, None, :]).transpose(2, 0, 1))  # (C, n, m), unit rows
    ws = np.ascontiguousarray((w * rs).T)  # (C, n)
    lo_c = np.ascontiguousarray(np.broadcast_to(lo, (m, C)).T)
    hi_c = np.ascontiguousarray(np.broadcast_to(hi, (m, C)).T)
    AtA = np.einsum("cim,cik->cmk", As, As)
    Atw = np.einsum("cim,ci->cm", As, ws)
    eye = np.eye(m)

    def objective(T: FloatArray, k: NDArray[np.intp], lam: float) -> FloatArray:
        """Penalised objective of T (..., K, m) at the poses k."""
        r = np.einsum("kim,...km->...ki", As[k], T) - ws[k]
        lo_k, hi_k = lo_c[k], hi_c[k]
        pen = (r * r).sum(-1)
        pen += (np.minimum(T - lo_k, 0.0) ** 2).sum(-1) + (np.maximum(T - hi_k, 0.0) ** 2).sum(-1)
        return ((T - lo_k) ** 2).sum(-1) + lam * pen

    T = lo_c.copy()
    converged = np.ones(C, dtype=bool)
    for lam in lambdas:
        k = np.arange(C)
        for _ in range(newton_iters):
            Tk, lo_k, hi_k = T[k], lo_c[k], hi_c[k]
            below, above = Tk < lo_k, Tk > hi_k
            act = (below | above).astype(np.float64)
            H = eye + lam * (AtA[k] + act[:, :, None] * eye)
            rhs = lo_k + lam * (Atw[k] + np.where(below, lo_k, hi_k) * act)
            d = np.linalg.solve(H, rhs[..., None])[..., 0] - Tk
            # Newton step of the current piece; backtrack on a grid if it leaves the piece badly
            f = objective(Tk[None] + _STEPS[:, None, None] * d[None], k, lam)
            best = np.argmin(f, axis=0)
            Tk = Tk + _STEPS[best][:, None] * d
            T[k] = Tk
            same = np.all(((Tk < lo_k) == below) & ((Tk > hi_k) == above), axis=-1)
            done = same & (best == 0)
            k = k[~done]
            if k.size == 0:
                break
        converged[k] = False
    status = np.where(converged, SOLVE_OK, SOLVE_INFEASIBLE).astype(np.int8)
    # the shared rank test, and the method's own: with lambda_max sigma_min(A')^2 < 1 the penalty
    # on the weakest direction of A' T = w' weighs less than the objective (sigma < 1e-5 for the
    # default schedule; its error grows as 1 / (lambda sigma^2), docs/tension.md)
    floors = _RankFloor(lo_c.T, hi_c.T, at_least=1.0 / np.sqrt(max(lambdas)))
    status[~_Factor(At, floors).ok] = SOLVE_RANK_DEFICIENT
    return np.ascontiguousarray(T.T), status


def penalty(
    A: ArrayLike,
    w: ArrayLike,
    t_min_N: ArrayLike,
    t_max_N: ArrayLike,
    *,
    lambdas: tuple[float, ...] = PENALTY_LAMBDAS,
) -> TensionResult:
    """The paper's penalty-function method: min ``|T - T_min|_2`` with the constraints as penalties.

    Minimises ``|T - t_min|^2 + lambda (|A' T - w'|^2 + |min(T - t_min, 0)|^2 +
    |max(T - t_max, 0)|^2)`` (``A'``, ``w'``: unit-norm rows) for each lambda of the increasing
    schedule ``lambdas``, warm started from the previous stage (from ``T = t_min`` at first); each
    stage is a convex piecewise quadratic solved exactly by a semismooth Newton (active-set)
    iteration.  The squared norm replaces the paper's norm (same minimiser, smooth).  The result
    approaches the exact min ``|T - T_min|_2`` solution as lambda grows (error O(1/lambda), see
    docs/tension.md); ``feasible`` uses the same tolerance as the other methods.  Besides the
    shared rank test, a pose with ``max(lambdas) sigma_min(A')^2 < 1`` is ``SOLVE_RANK_DEFICIENT``:
    the penalty on the weakest direction of ``A' T = w'`` weighs less than the objective there
    (sigma < 1e-5 for the default schedule); above it the error still grows as
    1 / (lambda sigma^2), 1.4e-3 N at sigma 1e-2 on the flat rig.
    """
    A_, w_, lo, hi = check_problem(A, w, t_min_N, t_max_N)
    lams = tuple(float(x) for x in lambdas)
    if not lams or any(not (x > 0) for x in lams):
        raise InputError(f"lambdas: expected positive penalty weights, got {lambdas!r}")

    def kernel(
        At: FloatArray, w: FloatArray, lo: FloatArray, hi: FloatArray
    ) -> tuple[FloatArray, IntArray]:
        return _penalty_kernel(At, w, lo, hi, lams)

    return _Chunked(A_, w_, lo, hi).run(
        kernel, (), "min |T - T_min|_2 (penalty, lambda schedule)", "penalty"
    )


# ---------------------------------------------------------------------------------------------


class Method(Protocol):
    """A tension-distribution method: ``(A, w, t_min_N, t_max_N, **options) -> TensionResult``."""

    def __call__(
        self, A: ArrayLike, w: ArrayLike, t_min_N: ArrayLike, t_max_N: ArrayLike, /
    ) -> TensionResult: ...


METHODS: dict[str, Method] = {
    "closed-form": closed_form,
    "improved-closed-form": improved_closed_form,
    "penalty": penalty,
    "exact": exact,
}
"""Registered tension-distribution methods by name."""


def distribute(
    method: str,
    A: ArrayLike,
    w: ArrayLike,
    t_min_N: ArrayLike,
    t_max_N: ArrayLike,
    **options: Any,
) -> TensionResult:
    """Run the registered tension-distribution ``method`` (see :data:`METHODS`).

    ``options`` go to the method (``t_ref_N`` for ``exact``, ``lambdas`` for ``penalty``).
    """
    try:
        fn = METHODS[method]
    except KeyError:
        raise InputError(f"method: expected one of {sorted(METHODS)}, got {method!r}") from None
    try:
        return fn(A, w, t_min_N, t_max_N, **options)  # type: ignore[call-arg]
    except TypeError as exc:
        if options:
            raise InputError(f"{method}: unsupported options {sorted(options)}: {exc}") from None
        raise
