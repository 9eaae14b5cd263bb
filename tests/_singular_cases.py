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
