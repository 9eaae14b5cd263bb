"""The sample clock of a sensor stream from its reception times and its sample counter.

A load cell samples at a fixed rate on its own clock; the recorder stamps each sample with the host's
time of *reception*, which adds a latency that is never negative and comes in bursts when the host is
busy (tens of milliseconds on a loaded machine).  Point windows, spectra and the phase of a motion
need the sampling instants, not the bursts.

With the sample counter k (lost samples still count), the instants lie on a line
``t_k = t_0 + k dt`` and each reception time is ``t_rx,k = t_k + latency_k``, ``latency_k >= 0``.
The line is the lower envelope of the points ``(k, t_rx,k)``: of the edges of their lower convex
hull, the one that minimises the total latency (a two-variable linear programme, whose optimum is a
hull edge, found here by a golden-section search on the slope) — so the least-delayed samples fix
the clock and a burst moves nothing.  Over a long run
the sensor's crystal and the host's clock drift apart (tens of ppm): the fit is made on segments of
``segment_s`` seconds and the segments' lines are joined where they meet their neighbours' middles
(continuous, piecewise linear).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import InputError

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class SampleClock:
    """t_ns: (n,) the sampling instants (int64 ns); period_ns: the mean sample period; latency_ns:
    (n,) reception time minus instant (>= 0 up to rounding); segments: how many lines were fitted."""

    t_ns: NDArray[np.int64]
    period_ns: float
    latency_ns: FloatArray
    segments: int


def _lower_edge(k: FloatArray, t: FloatArray) -> tuple[float, float]:
    """(t0, dt) of the line below every point (k, t) with the least total distance to them.

    For a slope dt the best intercept is ``min(t - dt k)``; the total latency then is
    ``-(n min(t - dt k) + dt sum(k)) + sum(t)``, convex in dt (a maximum of linear functions):
    golden-section search around the mean slope, each step one vectorised pass."""
    n = k.size
    if n < 2 or k[-1] <= k[0]:
        return float(np.min(t)), 0.0
    rough = (t[-1] - t[0]) / (k[-1] - k[0])
    span = max(abs(rough) * 0.05, 1e-3)
    lo, hi = rough - span, rough + span
    sk = float(np.sum(k))

    def cost(dt: float) -> float:
        return -(n * float(np.min(t - dt * k)) + dt * sk)

    g = (np.sqrt(5.0) - 1.0) / 2.0
    a, b = lo + (1 - g) * (hi - lo), lo + g * (hi - lo)
    fa, fb = cost(a), cost(b)
    for _ in range(80):
        if fa <= fb:
            hi, b, fb = b, a, fa
            a = lo + (1 - g) * (hi - lo)
            fa = cost(a)
        else:
            lo, a, fa = a, b, fb
            b = lo + g * (hi - lo)
            fb = cost(b)
    dt = 0.5 * (lo + hi)
    return float(np.min(t - dt * k)), float(dt)


def sample_clock(t_rx_ns: ArrayLike, counter: ArrayLike, segment_s: float = 60.0) -> SampleClock:
    """The sampling instants (see the module docstring) of samples received at ``t_rx_ns`` (n,)
    (int ns) with the unwrapped, increasing sample counter ``counter`` (n,)."""
    t = np.asarray(t_rx_ns, dtype=np.int64)
    c = np.asarray(counter, dtype=np.int64)
    n = t.shape[0]
    if c.shape != (n,):
        raise InputError(f"counter: expected ({n},), got {c.shape}")
    if n < 2:
        return SampleClock(t.copy(), float("nan"), np.zeros(n), 0)
    if np.any(np.diff(c) <= 0):
        raise InputError("counter: expected a strictly increasing sample counter")
    k = (c - c[0]).astype(np.float64)
    tr = (t - t[0]).astype(np.float64)
    period = tr[-1] / k[-1] if k[-1] > 0 else float("nan")
    per_seg = max(int(segment_s * 1e9 / period), 16) if np.isfinite(period) and period > 0 else n
    bounds = list(range(0, n, per_seg))
    if len(bounds) > 1 and n - bounds[-1] < per_seg // 2:
        bounds.pop()  # a short tail joins the segment before it
    edges = [*bounds, n]
    lines = [_lower_edge(k[a:b], tr[a:b]) for a, b in zip(edges[:-1], edges[1:], strict=True)]
    if len(lines) == 1:
        t0, dt = lines[0]
        inst = t0 + dt * k
    else:  # piecewise linear through each segment's line at its middle
        mid_k = np.array(
            [0.5 * (k[a] + k[b - 1]) for a, b in zip(edges[:-1], edges[1:], strict=True)]
        )
        mid_t = np.array([t0 + dt * km for (t0, dt), km in zip(lines, mid_k, strict=True)])
        inst = np.interp(k, mid_k, mid_t)
        first, last = lines[0], lines[-1]
        inst = np.where(k < mid_k[0], first[0] + first[1] * k, inst)
        inst = np.where(k > mid_k[-1], last[0] + last[1] * k, inst)
    t_ns = t[0] + np.rint(inst).astype(np.int64)
    return SampleClock(t_ns, float(np.mean([dt for _, dt in lines])), tr - inst, len(lines))
