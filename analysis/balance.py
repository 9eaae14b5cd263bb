"""Steady test points of a balance run: sample masks, point detection and per-point statistics.

Pure functions over arrays (integer ns times, SI values), O(n) in the number of samples, NaN-safe.

- :func:`sample_mask` says, per sample, why it cannot be used (status bits of the load cells, a
  counter gap, a NaN, a flagged pose) as a bit field; a sample is usable when its bits are 0.
- :func:`steady_points` finds steady stretches from the signals alone: at every sample the mean of
  the next window minus the mean of the previous one is compared with a band set from the *measured*
  noise of that difference (a robust spread over the whole run), so it works at any sampling rate and
  noise level (the paper's camera at 0.5 mm / 0.1 deg as well as a better one).  Both ends of every
  steady stretch are trimmed by ``trim_s``.
- :func:`points_from_events` turns test-point start/end times (the ``/events`` stream) into the same
  index ranges; events define the points where a run has them, detection is used otherwise.
- :func:`point_stats` gives per-point means, standard deviations and counts over the usable samples
  (bincount over sample labels: masked samples and NaN never reach a sum).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._checks import check_trailing
from .conventions import (
    MASK_COUNTER_GAP,
    MASK_NAMES,
    MASK_NAN,
    MASK_POSE,
    STATUS_ALL,
)
from .errors import InputError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


def mask_words(bits: int) -> list[str]:
    """The names of the bits set in ``bits`` (in bit order)."""
    return [name for bit, name in MASK_NAMES.items() if bits & bit]


def sample_mask(
    values: ArrayLike,
    status: ArrayLike | None = None,
    counter: ArrayLike | None = None,
    counter_modulus: int = 256,
    pose_bad: ArrayLike | None = None,
) -> NDArray[np.int64]:
    """Per-sample mask bits (n,): 0 for a usable sample.

    values: (n,) or (n, c) readings (a NaN or inf anywhere in a row sets :data:`MASK_NAN`);
    status: (n,) or (n, c) integer status words (:data:`cdpr.analysis.conventions.STATUS_NAMES`:
    saturated, slack, stale, bad frame, gap, sensor fault; OR-ed over the channels); counter:
    (n,) sample counter counting up by one modulo ``counter_modulus``: a jump marks the sample
    after it with :data:`MASK_COUNTER_GAP`;
    pose_bad: (n,) bool, a flagged pose (e.g. too few markers, large reprojection error).
    """
    v = np.asarray(values, dtype=np.float64)
    if v.ndim not in (1, 2):
        raise InputError(f"values: expected shape (n,) or (n, c), got {v.shape}")
    n = v.shape[0]
    finite = np.isfinite(v) if v.ndim == 1 else np.isfinite(v).all(axis=1)
    bits = np.where(finite, 0, MASK_NAN).astype(np.int64)
    if status is not None:
        s = np.asarray(status)
        if s.shape[0] != n or s.ndim > 2 or s.dtype.kind not in "iu":
            raise InputError(f"status: expected integer (n,) or (n, c) with n={n}, got {s.shape}")
        s = s.astype(np.int64)
        if s.ndim == 2:
            s = np.bitwise_or.reduce(s, axis=1)
        bits |= s & STATUS_ALL  # every status bit makes a sample unusable
    if counter is not None:
        c = np.asarray(counter)
        if c.shape != (n,) or c.dtype.kind not in "iu":
            raise InputError(f"counter: expected integer (n,) with n={n}, got {c.shape}")
        if counter_modulus < 2:
            raise InputError(f"counter_modulus: expected >= 2, got {counter_modulus}")
        step = np.mod(np.diff(c.astype(np.int64)), counter_modulus)
        bits[1:] |= np.where(step != 1, MASK_COUNTER_GAP, 0)
    if pose_bad is not None:
        pb = np.asarray(pose_bad, dtype=bool)
        if pb.shape != (n,):
            raise InputError(f"pose_bad: expected (n,) with n={n}, got {pb.shape}")
        bits |= np.where(pb, MASK_POSE, 0)
    return bits


@dataclass(frozen=True)
class SteadyRule:
    """How steady points are detected (used when a run has no test-point events).

    window_s: length of the two windows whose means are compared at every sample.
    k_sigma: a sample is in a transition where the windows' difference exceeds ``k_sigma`` times
        its measured noise (robust spread over the run) in any channel.
    speed_floor_mps, position_floor_m, angle_floor_rad: the smallest bands (a perfectly quiet
        channel still tolerates these); speed_rel: the airspeed band is at least this fraction
        of the speed.
    trim_s: time dropped at *both* ends of every steady stretch.
    min_duration_s: shorter points (after trimming) are dropped.
    wind_off_mps: airspeed below which a point is a wind-off tare.
    """

    window_s: float = 0.2
    k_sigma: float = 6.0
    speed_floor_mps: float = 0.05
    speed_rel: float = 0.01
    position_floor_m: float = 2e-5
    angle_floor_rad: float = float(np.deg2rad(0.002))
    trim_s: float = 0.1
    min_duration_s: float = 0.2
    wind_off_mps: float = 1.0


def steady_points(
    t_ns: ArrayLike,
    airspeed_mps: ArrayLike | None,
    poses: ArrayLike,
    usable: ArrayLike | None = None,
    rule: SteadyRule = SteadyRule(),
) -> list[tuple[int, int]]:
    """Index ranges ``[start, stop)`` of the steady points of a run (one pass, O(n)).

    t_ns: (n,) strictly increasing times; airspeed_mps: (n,) or None (no tunnel data: the pose
    alone decides); poses: (n, 6) ``[x, y, z, roll, pitch, yaw]`` (m, rad), NaN allowed;
    usable: (n,) bool (default: all finite samples).

    At sample i, ``D_i = mean(x[i:i+w]) - mean(x[i-w:i])`` per channel (w samples ~ window_s);
    its noise sigma is estimated robustly from the run itself (the 10 % quantile of ``|D|``, so
    transitions, however many, only fill the tail).  A sample is in a transition when
    ``|D| > max(k_sigma * sigma, floor)`` in any channel (for the airspeed also ``speed_rel`` times
    the speed: tunnel noise grows with it); the maximal stretches outside transitions, less
    ``trim_s`` at both ends, are the points.  The windows run over the usable samples only, so a
    masked stretch (saturated cell, NaN) inside a steady point neither splits it nor biases it.
    """
    t = np.asarray(t_ns, dtype=np.int64)
    n = t.shape[0]
    q = np.asarray(poses, dtype=np.float64)
    if q.shape != (n, 6):
        raise InputError(f"poses: expected ({n}, 6) for {n} times, got {q.shape}")
    chans = [q]
    floors = [rule.position_floor_m] * 3 + [rule.angle_floor_rad] * 3
    if airspeed_mps is not None:
        v = np.asarray(airspeed_mps, dtype=np.float64)
        if v.shape != (n,):
            raise InputError(f"airspeed_mps: expected ({n},), got {v.shape}")
        chans.insert(0, v[:, None])
        floors.insert(0, rule.speed_floor_mps)
    x = np.concatenate(chans, axis=1)
    ok: NDArray[np.bool_] = np.asarray(np.isfinite(x).all(axis=1))
    if usable is not None:
        u = np.asarray(usable, dtype=bool)
        if u.shape != (n,):
            raise InputError(f"usable: expected ({n},), got {u.shape}")
        ok &= u
    if n < 4 or ok.sum() < 4:
        return []
    if np.any(np.diff(t) <= 0):
        raise InputError("t_ns: expected strictly increasing times")
    # work on the usable samples only: a masked stretch neither splits a point nor enters a mean;
    # a change of level across it still shows in the windows on either side
    idx = np.flatnonzero(ok)
    xc = x[idx] if idx.size < n else x  # x is this function's own array
    nc = idx.size
    dt = float(np.median(np.diff(t[idx])))
    w = max(2, int(round(rule.window_s * 1e9 / dt)))
    med = np.median(xc, axis=0)
    v_med = float(med[0]) if airspeed_mps is not None else 0.0
    xc -= med
    c = np.empty((nc + 1, xc.shape[1]))
    c[0] = 0.0
    np.cumsum(xc, axis=0, out=c[1:])
    del x, xc
    if nc < 2 * w:
        return []
    # at usable sample i: mean of [i, i + w) minus mean of [i - w, i), for w <= i <= nc - w
    # (slices of the cumulative sums c[i + w], c[i], c[i - w]: no (n, k) copies)
    hi, mid, lo = c[2 * w : nc + 1], c[w : nc - w + 1], c[: nc - 2 * w + 1]
    D = hi - mid
    D -= mid
    D += lo
    D /= w
    absD = np.abs(D, out=D)  # only |D| is used from here on
    # the 10 % quantile of |D| over the run: |N(0, sigma)| has its 10 % quantile at 0.1257 sigma;
    # robust while at least ~ a fifth of the run is steady (transitions inflate only the tail)
    sigma = np.quantile(absD, 0.1, axis=0) / 0.1257
    band = np.maximum(rule.k_sigma * sigma, np.asarray(floors))
    # a transition at sample i spreads over (i - w, i + w): the windows see it there.  The first
    # and last w samples have one window only: they share the verdict of the nearest pair.
    if airspeed_mps is None:
        out = (absD > band).any(axis=1)
    else:  # tunnel noise grows with speed: a relative floor for the airspeed as well
        v_level = np.abs((hi[:, 0] - mid[:, 0]) / w + v_med)
        out = (absD[:, 1:] > band[1:]).any(axis=1)
        out |= absD[:, 0] > np.maximum(band[0], rule.speed_rel * v_level)
    sc = np.empty(nc, bool)
    sc[w : nc - w + 1] = ~out
    sc[:w] = sc[w]
    sc[nc - w + 1 :] = sc[nc - w]
    # back to all samples: a masked sample is steady when the usable samples on both sides are
    pos = np.cumsum(ok) - 1  # index into idx of the last usable sample at or before each sample
    prev_ok = np.where(pos >= 0, sc[np.maximum(pos, 0)], False)
    nxt = np.minimum(pos + (~ok), nc - 1)  # first usable sample at or after
    next_ok = sc[np.maximum(nxt, 0)]
    steady = np.where(ok, sc[np.maximum(pos, 0)], prev_ok & next_ok & (pos >= 0))
    edges = np.flatnonzero(np.diff(np.concatenate([[0], steady.astype(np.int8), [0]])))
    starts, stops = edges[0::2], edges[1::2]
    trim = int(rule.trim_s * 1e9)
    a = np.searchsorted(t, t[starts] + trim, side="left")
    b = np.searchsorted(t, t[stops - 1] - trim, side="right")
    keep = (b > a) & (
        (t[np.maximum(b - 1, 0)] - t[np.minimum(a, n - 1)]) >= rule.min_duration_s * 1e9
    )
    return [(int(i), int(j)) for i, j in zip(a[keep], b[keep], strict=True)]


def points_from_events(
    t_ns: ArrayLike, start_ns: ArrayLike, stop_ns: ArrayLike
) -> list[tuple[int, int]]:
    """Index ranges ``[start, stop)`` of the samples at times within each ``[start_ns, stop_ns]``.

    t_ns: (n,) increasing sample times; start_ns, stop_ns: (s,) test-point start and end times.
    A point with no sample inside gives an empty range (its statistics are NaN, count 0).
    """
    t = np.asarray(t_ns, dtype=np.int64)
    a0 = np.asarray(start_ns, dtype=np.int64)
    b0 = np.asarray(stop_ns, dtype=np.int64)
    if a0.shape != b0.shape or a0.ndim != 1:
        raise InputError(
            f"start_ns, stop_ns: expected equal (s,) shapes, got {a0.shape}, {b0.shape}"
        )
    if np.any(b0 < a0):
        i = int(np.flatnonzero(b0 < a0)[0])
        raise InputError(f"test point {i}: ends at {b0[i]} ns before it starts at {a0[i]} ns")
    a = np.searchsorted(t, a0, side="left")
    b = np.searchsorted(t, b0, side="right")
    return [(int(i), int(j)) for i, j in zip(a, b, strict=True)]


@dataclass(frozen=True)
class PointStats:
    """Statistics over the usable samples of each point (s points, c channels).

    mean, sd: (s, c) (NaN where a point has fewer than 1 / 2 usable samples);
    n_samples: (s,) samples in the range; n_used: (s,) usable ones; n_masked = n_samples - n_used;
    masked_bits: (s,) OR of the mask bits of the point's samples.
    """

    mean: FloatArray
    sd: FloatArray
    n_samples: IntArray
    n_used: IntArray
    masked_bits: IntArray

    @property
    def n_masked(self) -> IntArray:
        return self.n_samples - self.n_used

    @property
    def sem(self) -> FloatArray:
        """Standard error of the means (s, c)."""
        return self.sd / np.sqrt(np.maximum(self.n_used, 1))[:, None]


def point_stats(
    values: ArrayLike, ranges: list[tuple[int, int]], mask_bits: ArrayLike | None = None
) -> PointStats:
    """Means and standard deviations of ``values`` (n,) or (n, c) over each ``[start, stop)`` range,
    using only samples whose mask bits are 0 and whose values are finite (O(n): bincount over
    per-sample point labels; ranges must not overlap)."""
    x = np.asarray(values, dtype=np.float64)
    if x.ndim == 1:
        x = x[:, None]
    if x.ndim != 2:
        raise InputError(f"values: expected (n,) or (n, c), got {x.shape}")
    n, c = x.shape
    bits = np.zeros(n, np.int64) if mask_bits is None else np.asarray(mask_bits, dtype=np.int64)
    if bits.shape != (n,):
        raise InputError(f"mask_bits: expected ({n},), got {bits.shape}")
    s = len(ranges)
    idx = np.asarray(ranges, dtype=np.int64).reshape(s, 2)
    if np.any(idx[:, 1] < idx[:, 0]) or np.any(idx < 0) or np.any(idx > n):
        raise InputError(f"ranges: expected 0 <= start <= stop <= {n}")
    order = np.argsort(idx[:, 0], kind="stable")
    if s > 1 and np.any(idx[order][1:, 0] < idx[order][:-1, 1]):
        raise InputError("ranges: expected non-overlapping ranges")
    label = np.full(n + 1, -1, np.int64)
    # label each sample with its point: +1 at start, -1 at stop of an "index + 1" running sum
    mark = np.zeros(n + 1, np.int64)
    np.add.at(mark, idx[:, 0], np.arange(1, s + 1))
    np.add.at(mark, idx[:, 1], -np.arange(1, s + 1))
    label = np.cumsum(mark)[:n] - 1
    finite = np.isfinite(x)
    use = (label >= 0) & (bits == 0) & finite.all(axis=1)
    lab = np.where(use, label, s)  # s = the bin of unused samples
    cnt = np.bincount(lab, minlength=s + 1)[:s].astype(np.int64)
    xz = np.where(use[:, None], x, 0.0)
    in_pt = label >= 0
    n_samples = np.bincount(np.where(in_pt, label, s), minlength=s + 1)[:s].astype(np.int64)
    masked = np.zeros(s + 1, np.int64)
    np.bitwise_or.at(
        masked, np.where(in_pt, label, s), np.where(finite.all(axis=1), bits, bits | MASK_NAN)
    )
    mean = np.empty((s, c))
    var = np.empty((s, c))
    for j in range(c):  # loop over channels, not samples
        sm = np.bincount(lab, weights=xz[:, j], minlength=s + 1)[:s]
        with np.errstate(invalid="ignore", divide="ignore"):
            mu = sm / cnt
        dev = np.where(use, xz[:, j] - np.append(mu, 0.0)[lab], 0.0)
        ss = np.bincount(lab, weights=dev * dev, minlength=s + 1)[:s]
        mean[:, j] = mu
        with np.errstate(invalid="ignore", divide="ignore"):
            var[:, j] = np.where(cnt > 1, ss / (cnt - 1), np.nan)
    mean[cnt == 0] = np.nan
    return PointStats(mean, np.sqrt(var), n_samples, cnt, masked[:s])


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


def nearest_tare(
    pose_mean: ArrayLike,
    is_tare: ArrayLike,
    start_ns: ArrayLike,
    position_tol_m: float,
    angle_tol_rad: float,
) -> IntArray:
    """For every point, the index of the wind-off point at the same pose (within tolerances)
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
