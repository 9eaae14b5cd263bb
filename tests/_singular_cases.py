"""Tension problems with a prescribed smallest singular value and a known optimum.

Written independently of ``cdpr.analysis.tension``: the optimum comes from the KKT conditions by
construction, not from a solver.  For

    min 1/2 |T - T_ref|^2  s.t.  A T = w,  t_min <= T <= t_max

a point ``T*`` is the (unique) optimum when ``A T* = w``, ``t_min <= T* <= t_max`` and
``T* - T_ref = A^T y + mu_lo - mu_hi`` with ``mu_lo, mu_hi >= 0`` zero off the active bounds.
So: draw ``A = U diag(s) V^T`` (orthogonal U, V; ``s`` with the chosen smallest value), ``T*``,
the active cables, ``y`` and ``mu``; then ``T_ref = T* - A^T y - mu_lo + mu_hi``, ``w = A T*``
and limits that make the chosen cables active and leave the others a margin.
"""

from __future__ import annotations

import numpy as np


def _orthogonal(rng: np.random.Generator, k: int, size: int) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(size, k, k)))
    return q * np.sign(np.einsum("...ii->...i", r))[:, None, :]


def singular_cases(sigma_min: float, size: int, seed: int, n: int = 6, m: int = 8):
    """``size`` problems whose A (unit-scale rows) has smallest singular value ``sigma_min``.

    Returns A (size, n, m), w (size, n), t_min, t_max, t_ref (size, m) and the optimum T* (size, m).
    Zero, one or two cables are active at the optimum (at t_min or t_max), in equal shares.
    ``sigma_min = 0`` gives rank-5 matrices (the optimum still exists: w is in the range of A).
    """
    rng = np.random.default_rng(seed)
    U = _orthogonal(rng, n, size)
    V = _orthogonal(rng, m, size)[:, :, :n]
    s = np.empty((size, n))
    s[:, : n - 1] = rng.uniform(0.3, 1.0, (size, n - 1))
    s[:, n - 1] = sigma_min
    A = np.einsum("kij,kj,klj->kil", U, s, V)
    T = rng.uniform(60.0, 240.0, (size, m))
    y = rng.normal(0.0, 20.0, (size, n))
    n_active = np.arange(size) % 3
    active = np.zeros((size, m), dtype=bool)
    at_hi = rng.random((size, m)) < 0.5
    for k in range(size):
        active[k, rng.choice(m, n_active[k], replace=False)] = True
    mu = np.where(active, rng.uniform(5.0, 40.0, (size, m)), 0.0)
    ref = T - np.einsum("kim,ki->km", A, y) - np.where(at_hi, -mu, mu)
    w = np.einsum("kim,km->ki", A, T)
    lo = T - rng.uniform(10.0, 50.0, (size, m))
    hi = T + rng.uniform(10.0, 50.0, (size, m))
    lo = np.where(active & ~at_hi, T, lo)
    hi = np.where(active & at_hi, T, hi)
    return A, w, lo, hi, ref, T


def vertex_cases(
    sigma_G: float, size: int, seed: int, sigma_A: float = 0.3, n: int = 6, m: int = 8
):
    """``size`` problems whose optimum is a vertex of two limits that are nearly parallel in the
    null space of A: the null-space rows of the two active cables are at an angle ~ ``sigma_G``,
    while A itself is well conditioned (smallest singular value ``sigma_A``).

    The smallest singular value of A restricted to the six other cables is then ~ sigma_A sigma_G:
    the answer's sensitivity, which sigma_min(A) alone does not show.  The optimum by the same KKT
    construction as :func:`singular_cases`; returns A, w, t_min, t_max, t_ref, T* and the mask
    (size, m) of the two active cables.
    """
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(size):
        Q = np.linalg.qr(rng.normal(size=(m, m)))[0]
        N = Q[:, :2].copy()
        i, j = rng.choice(m, 2, replace=False)
        N[j] = N[i] * rng.uniform(0.5, 1.5) + sigma_G * np.linalg.norm(N[i]) * rng.normal(size=2)
        N = np.linalg.qr(N)[0]  # still nearly parallel rows i, j
        P = np.eye(m) - N @ N.T
        B = np.linalg.qr(P @ rng.normal(size=(m, n)))[0].T  # orthonormal rows: the row space
        U = np.linalg.qr(rng.normal(size=(n, n)))[0]
        s = rng.uniform(0.3, 1.0, n)
        s[-1] = sigma_A
        A = U @ np.diag(s) @ B
        T = rng.uniform(60.0, 240.0, m)
        active = np.zeros(m, dtype=bool)
        active[[i, j]] = True
        at_hi = rng.random(m) < 0.5
        mu = np.where(active, rng.uniform(5.0, 40.0, m), 0.0)
        ref = T - A.T @ rng.normal(0.0, 20.0, n) - np.where(at_hi, -mu, mu)
        lo = np.where(active & ~at_hi, T, T - rng.uniform(10.0, 50.0, m))
        hi = np.where(active & at_hi, T, T + rng.uniform(10.0, 50.0, m))
        out.append((A, A @ T, lo, hi, ref, T, active))
    A, w, lo, hi, ref, T, active = (np.array(x) for x in zip(*out, strict=True))
    return A, w, lo, hi, ref, T, active


def with_sigma_min(A: np.ndarray, sigma_min, iters: int = 5) -> np.ndarray:
    """Structure matrices A (K, n, m) moved to the nearest matrices (SVD) whose form with unit-norm
    rows has the smallest singular value ``sigma_min`` (scalar or (K,)), each row keeping its norm:
    a real pose's geometry brought to a chosen distance from singularity.  Iterated, because putting
    the norms back moves the unit-row form's singular values a little."""
    A = np.array(A, dtype=float)
    for _ in range(iters):
        rn = np.linalg.norm(A, axis=-1, keepdims=True)
        U, s, Vt = np.linalg.svd(A / rn, full_matrices=False)
        s[:, -1] = sigma_min
        A = np.einsum("kij,kj,kjl->kil", U, s, Vt) * rn
    return A


def sigma_free(A: np.ndarray, at_limit: np.ndarray) -> np.ndarray:
    """Smallest singular value (K,) of A (K, n, m) with unit-norm rows, restricted to the cables
    not at a limit (mask at_limit (K, m)): min(n, free) values per case, numpy's SVD."""
    As = A / np.linalg.norm(A, axis=-1, keepdims=True)
    out = np.empty(A.shape[0])
    for k in range(A.shape[0]):
        free = ~at_limit[k]
        sv = np.linalg.svd(As[k][:, free], compute_uv=False)
        out[k] = sv[min(A.shape[1], free.sum()) - 1] if free.any() else np.inf
    return out


def floor_from_spec(t_min, t_max, t_ref) -> np.ndarray:
    """The rank floor as docs/tension.md states it, written out here: 2 eps scale / max(1e-6 N,
    1e-10 scale) with scale = sqrt(m) max_j max(|t_min_j|, |t_max_j|, |t_ref_j|)."""
    big = np.maximum(np.maximum(np.abs(t_min), np.abs(t_max)), np.abs(t_ref))
    scale = np.sqrt(big.shape[-1]) * big.max(axis=-1)
    return 2.0 * np.finfo(float).eps * scale / np.maximum(1e-6, 1e-10 * scale)
