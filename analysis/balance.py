"""Post-processing of a balance run: steady test points, their statistics and the tension check.

Pure functions over arrays (integer ns times, SI values).  A run is cut into *steady segments*:
maximal stretches where the airspeed and the pose stay within tolerances, after a settling time;
wind-off segments are the tares.  Per segment the mean tensions and pose give the recovered wrench
(:mod:`cdpr.analysis.wrench`), and the tensions the distribution method would command for that
wrench give the paper's "measured vs simulated" check.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._checks import check_trailing
from .errors import InputError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class SegmentRule:
    """How steady segments are found.

    wind_off_mps: airspeed below which the wind is off (a tare).
    speed_tol_rel, speed_tol_mps: a segment's airspeed stays within ``max(rel * V, abs)`` of its start.
    position_tol_m, angle_tol_rad: a segment's pose stays within these of its start.
    settle_s: time dropped at the start of every segment (transients after a change).
    min_duration_s: shorter segments (after settling) are dropped.
    """

    wind_off_mps: float = 1.0
    speed_tol_rel: float = 0.03
    speed_tol_mps: float = 0.3
    position_tol_m: float = 0.001
    angle_tol_rad: float = float(np.deg2rad(0.1))
    settle_s: float = 0.3
    min_duration_s: float = 0.4


def steady_segments(
    t_ns: ArrayLike, airspeed_mps: ArrayLike, poses: ArrayLike, rule: SegmentRule = SegmentRule()
) -> list[tuple[int, int]]:
    """Index ranges ``[start, stop)`` of the steady segments of a run.

    t_ns: (n,) increasing sample times; airspeed_mps: (n,) airspeed at those times; poses: (n, 6)
    ``[x, y, z, alpha, beta, gamma]`` (m, rad).  A new segment starts where the airspeed or the pose
    leaves the tolerance around the current segment's first sample (one pass, vectorised per
    segment); each segment then loses ``settle_s`` at its start and is kept if at least
    ``min_duration_s`` remains.
    """
    t = np.asarray(t_ns, dtype=np.int64)
    v = np.asarray(airspeed_mps, dtype=np.float64)
    q = check_trailing(poses, "poses", (6,))
    n = t.shape[0]
    if v.shape != (n,) or q.shape != (n, 6):
        raise InputError(
            f"t_ns (n,), airspeed_mps (n,), poses (n, 6) expected, got {t.shape}, {v.shape}, {q.shape}"
        )
    if n and np.any(np.diff(t) <= 0):
        raise InputError("t_ns: expected strictly increasing times")
    segments: list[tuple[int, int]] = []
    start = 0
    while start < n:
        tol_v = max(rule.speed_tol_rel * abs(v[start]), rule.speed_tol_mps)
        out = (
            (np.abs(v[start:] - v[start]) > tol_v)
            | (np.linalg.norm(q[start:, :3] - q[start, :3], axis=1) > rule.position_tol_m)
            | (np.abs(q[start:, 3:] - q[start, 3:]).max(axis=1) > rule.angle_tol_rad)
        )
        hit = np.flatnonzero(out)
        stop = start + int(hit[0]) if hit.size else n
        settled = start + int(np.searchsorted(t[start:stop], t[start] + int(rule.settle_s * 1e9)))
        if stop > settled and (t[stop - 1] - t[settled]) >= rule.min_duration_s * 1e9:
            segments.append((settled, stop))
        start = max(stop, start + 1)
    return segments


def interpolate_at(t_ns: ArrayLike, t_src_ns: ArrayLike, values: ArrayLike) -> FloatArray:
    """Linear interpolation of ``values`` (k,) or (k, d) sampled at ``t_src_ns`` onto ``t_ns`` (n,);
    held constant outside the source range."""
    t = np.asarray(t_ns, dtype=np.int64)
    ts = np.asarray(t_src_ns, dtype=np.int64)
    vals = np.asarray(values, dtype=np.float64)
    if ts.ndim != 1 or ts.shape[0] != vals.shape[0] or ts.shape[0] == 0:
        raise InputError(
            f"t_src_ns (k,) and values (k, ...) expected, got {ts.shape} and {vals.shape}"
        )
    x = (t - ts[0]).astype(np.float64)
    xs = (ts - ts[0]).astype(np.float64)
    if vals.ndim == 1:
        return np.interp(x, xs, vals)
    return np.stack([np.interp(x, xs, vals[:, k]) for k in range(vals.shape[1])], axis=1)


@dataclass(frozen=True)
class SegmentStats:
    """Statistics of steady segments (s segments, m cables).

    start_ns, stop_ns: (s,) first and last sample times; n: (s,) sample counts;
    tension_mean_N, tension_sd_N: (s, m); pose_mean: (s, 6); airspeed_mps: (s,).
    """

    start_ns: IntArray
    stop_ns: IntArray
    n: IntArray
    tension_mean_N: FloatArray
    tension_sd_N: FloatArray
    pose_mean: FloatArray
    airspeed_mps: FloatArray


def segment_stats(
    t_ns: ArrayLike,
    tensions_N: ArrayLike,
    poses: ArrayLike,
    airspeed_mps: ArrayLike,
    segments: list[tuple[int, int]],
) -> SegmentStats:
    """Means and standard deviations over each ``[start, stop)`` segment (cumulative sums, no loop
    over samples)."""
    t = np.asarray(t_ns, dtype=np.int64)
    T = np.asarray(tensions_N, dtype=np.float64)
    q = check_trailing(poses, "poses", (6,))
    v = np.asarray(airspeed_mps, dtype=np.float64)
    if not segments:
        raise InputError("segments: no steady segment in the run")
    idx = np.asarray(segments, dtype=np.int64)
    a, b = idx[:, 0], idx[:, 1]
    cnt = (b - a).astype(np.float64)

    def seg_mean(x: FloatArray) -> FloatArray:
        c = np.concatenate([np.zeros((1,) + x.shape[1:]), np.cumsum(x, axis=0)])
        return (c[b] - c[a]) / cnt.reshape((-1,) + (1,) * (x.ndim - 1))

    mean_T = seg_mean(T)
    var_T = np.maximum(seg_mean(T * T) - mean_T**2, 0.0) * (cnt / np.maximum(cnt - 1, 1))[:, None]
    return SegmentStats(
        start_ns=t[a],
        stop_ns=t[b - 1],
        n=(b - a).astype(np.int64),
        tension_mean_N=mean_T,
        tension_sd_N=np.sqrt(var_T),
        pose_mean=seg_mean(q),
        airspeed_mps=seg_mean(v),
    )


def nearest_tare(
    pose_mean: ArrayLike,
    is_tare: ArrayLike,
    start_ns: ArrayLike,
    position_tol_m: float,
    angle_tol_rad: float,
) -> IntArray:
    """For every segment, the index of the wind-off segment at the same pose (within tolerances)
    closest in time, or -1 when there is none."""
    q = check_trailing(pose_mean, "pose_mean", (6,))
    tare = np.asarray(is_tare, dtype=bool)
    t0 = np.asarray(start_ns, dtype=np.int64)
    same = (np.linalg.norm(q[:, None, :3] - q[None, :, :3], axis=-1) <= position_tol_m) & (
        np.abs(q[:, None, 3:] - q[None, :, 3:]).max(axis=-1) <= angle_tol_rad
    )
    ok = same & tare[None, :]
    dt = np.abs(t0[:, None] - t0[None, :]).astype(np.float64)
    dt[~ok] = np.inf
    best = np.argmin(dt, axis=1)
    return np.where(np.isfinite(dt[np.arange(len(q)), best]), best, -1).astype(np.int64)
