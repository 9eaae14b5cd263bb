"""The inputs of the reduction core from sample streams: per-point means and their covariance.

:func:`points_from_samples` turns the tension samples of a run (with their mask bits), its tunnel
stream and its pose stream into one :class:`~cdpr.analysis.reduction.Points` row per test point,
with the flag words of what was masked or missing (``input_flags``, raised by the core's first
stage).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .balance import PointStats, mask_words, point_stats
from .errors import InputError
from .longrun import MIN_N_EFF, long_run, window_long_runs
from .reduction import POSE, POSE_COV, Points, new_points

FloatArray = NDArray[np.float64]


def points_from_samples(
    *,
    kind: ArrayLike,
    ranges: list[tuple[int, int]],
    t_ns: ArrayLike,
    tensions_N: ArrayLike,
    mask_bits: ArrayLike,
    airspeed_mps: ArrayLike | None,
    density_kgpm3: ArrayLike | None,
    pose_t_ns: ArrayLike,
    poses: ArrayLike,
    pose_cov: ArrayLike | None,
    pose_sd_fallback: ArrayLike | None = None,
    pose_bad: ArrayLike | None = None,
    pose_sd_word: str = "pose_cov_nominal",
) -> tuple[Points, dict[str, NDArray[Any]]]:
    """Per-point inputs of the core from sample streams, and the point statistics.

    kind: (s,) point kinds; ranges: (s) ``[start, stop)`` indices into the tension samples
    (``t_ns`` (n,), ``tensions_N`` (n, m), ``mask_bits`` (n,) from
    :func:`cdpr.analysis.balance.sample_mask`); airspeed_mps, density_kgpm3: (n,) on the tension
    times, or None (no tunnel data: NaN, the coefficients stage flags ``no_airspeed``).
    The pose stream is separate (``pose_t_ns`` (k,), ``poses`` (k, 6), ``pose_cov`` (k, 6, 6) as
    the camera reports it per frame, ``pose_bad`` (k,) frames to drop): each point takes the frames
    inside its time span; the covariance of its mean pose is the mean reported covariance over the
    number of frames used.  Without a reported covariance, ``pose_sd_fallback`` (6,) (the camera's
    precision per frame) is used and the point flagged ``pose_sd_word`` (``pose_cov_nominal`` for
    the paper's constant, ``pose_cov_stated`` for a precision the lab stated); with neither, an
    error.

    Tension covariance: the covariance of each point's mean tensions from the data's own correlation
    in time and across cables (:func:`cdpr.analysis.longrun.window_long_runs`), with the samples'
    covariance ``tension_sample_cov_N2``, the usable count ``n_used``, the smallest effective
    sample count over the cables ``n_eff_min``; a window with fewer than
    :data:`cdpr.analysis.longrun.MIN_N_EFF` effective samples (or a fit that is not stationary)
    is flagged ``window_too_short`` with ``dwell_needed_s``, the point duration that would give
    that many at the same correlation.
    Flag words (``input_flags``): ``masked`` plus the mask words, ``no_samples`` (nothing usable),
    ``no_pose``, ``pose_flagged`` (some camera frames in the point dropped), ``pose_cov_nominal``.
    Returns the points and a dict of extra per-point columns (counts, start/stop times).
    """
    t = np.asarray(t_ns, dtype=np.int64)
    T = np.asarray(tensions_N, dtype=np.float64)
    bits = np.asarray(mask_bits, dtype=np.int64)
    s = len(ranges)
    st = point_stats(T, ranges, bits)
    idx = np.asarray(ranges, dtype=np.int64).reshape(s, 2)
    nonempty = idx[:, 1] > idx[:, 0]
    start_ns = np.where(nonempty, t[np.minimum(idx[:, 0], len(t) - 1)], 0)
    stop_ns = np.where(nonempty, t[np.maximum(idx[:, 1] - 1, 0)], 0)
    n = t.shape[0]

    def on_points(x: ArrayLike | None) -> FloatArray:
        if x is None:
            return np.full(s, np.nan)
        v = np.asarray(x, dtype=np.float64)
        if v.shape != (n,):
            raise InputError(f"tunnel stream: expected ({n},) on the tension times, got {v.shape}")
        return np.asarray(point_stats(v, ranges, bits).mean[:, 0], dtype=np.float64)

    V, rho = on_points(airspeed_mps), on_points(density_kgpm3)
    # pose stream: frames within each point's time span
    tp = np.asarray(pose_t_ns, dtype=np.int64)
    qp = np.asarray(poses, dtype=np.float64)
    if qp.shape != (tp.shape[0], 6):
        raise InputError(f"poses: expected ({tp.shape[0]}, 6), got {qp.shape}")
    pbad = np.zeros(tp.shape[0], bool) if pose_bad is None else np.asarray(pose_bad, dtype=bool)
    a = np.searchsorted(tp, start_ns, side="left")
    b = np.searchsorted(tp, stop_ns, side="right")
    pranges = [
        (int(i), int(j)) if ok else (int(i), int(i))
        for i, j, ok in zip(a, b, nonempty, strict=True)
    ]
    pbits = np.where(pbad, 1, 0).astype(np.int64)
    ps = point_stats(qp, pranges, pbits)
    nf = np.maximum(ps.n_used, 1).astype(np.float64)
    nominal = np.zeros(s, bool)
    if pose_cov is not None:
        C = np.asarray(pose_cov, dtype=np.float64)
        if C.shape != (tp.shape[0], 6, 6):
            raise InputError(f"pose_cov: expected ({tp.shape[0]}, 6, 6), got {C.shape}")
        cm = point_stats(C.reshape(-1, 36), pranges, pbits).mean.reshape(s, 6, 6)
        pcov = cm / nf[:, None, None]
    elif pose_sd_fallback is not None:
        sd = np.asarray(pose_sd_fallback, dtype=np.float64)
        if sd.shape != (6,):
            raise InputError(f"pose_sd_fallback: expected (6,), got {sd.shape}")
        pcov = np.broadcast_to(np.diag(sd**2), (s, 6, 6)) / nf[:, None, None]
        nominal[:] = True
    else:
        raise InputError("pose_cov: no covariance in the pose stream and no fallback given")
    frame_var = np.diagonal(pcov, axis1=1, axis2=2) * nf[:, None]  # one frame's variance (s, 6)
    rate_var = pose_rate_variance(tp, qp, pbad, pranges, frame_var)
    wander = np.flatnonzero(np.any(ps.sd**2 > 2.0 * frame_var, axis=1))  # beyond the camera's noise
    motion_cov = np.zeros((s, 6, 6))
    if wander.size:
        motion_cov[wander] = pose_motion_covariance(
            qp, pbits, [pranges[k] for k in wander], np.asarray(pcov)[wander]
        )
    # the covariance of each point's mean tensions from the data's own correlation (time and
    # across cables), not sd / sqrt(n): :mod:`cdpr.analysis.longrun`
    m = T.shape[1]
    runs = window_long_runs(T, ranges, bits)
    tcov = np.stack([lr.cov_of_mean for lr in runs]) if s else np.zeros((0, m, m))
    g0 = np.stack([lr.sample_cov for lr in runs]) if s else np.zeros((0, m, m))
    short = np.array([not lr.converged() for lr in runs], dtype=bool)
    min_n_eff = np.array([float(np.min(lr.n_eff())) if lr.n >= 2 else np.nan for lr in runs])
    pts = new_points(
        kind=kind,
        start_ns=start_ns,
        mid_ns=start_ns + (stop_ns - start_ns) // 2,
        tension_N=st.mean,
        tension_cov_N2=tcov,
        **{POSE: ps.mean, POSE_COV: np.array(pcov)},
        airspeed_mps=V,
        density_kgpm3=rho,
        input_flags=_input_words(st, ps, nominal, short & (st.n_used >= 2), pose_sd_word),
        tension_sample_cov_N2=g0,
        pose_rate_var=rate_var,
        pose_motion_cov=motion_cov,
        window_s=(stop_ns - start_ns) * 1e-9,
        n_used=st.n_used,
        longrun_bandwidth=np.array([lr.bandwidth for lr in runs], dtype=np.int64),
        n_eff_min=min_n_eff,
        dwell_needed_s=np.where(
            short, (stop_ns - start_ns) * 1e-9 * MIN_N_EFF / np.maximum(min_n_eff, 1e-9), np.nan
        ),
    )
    extra = {
        "start_ns": start_ns,
        "stop_ns": stop_ns,
        "n_samples": st.n_samples,
        "n_masked": st.n_masked,
        "n_pose_frames": ps.n_used,
        "tension_sd_N": st.sd,
    }
    return pts, extra


MAX_POSE_BLOCKS: int = 2000
"""The most frames (block means beyond) a point's pose long-run estimate is made from."""


def pose_motion_covariance(
    poses: ArrayLike,
    pose_bits: ArrayLike,
    ranges: list[tuple[int, int]],
    camera_cov_of_mean: ArrayLike,
) -> FloatArray:
    """The covariance (s, 6, 6) of each point's mean pose from the platform's own motion: the
    long-run covariance of the frames' mean (:func:`cdpr.analysis.longrun.window_long_runs`, the
    tensions' estimator) beyond the camera's noise (``camera_cov_of_mean`` (s, 6, 6)), kept only in
    the directions where it is beyond the estimate's own scatter (:func:`_significant_excess`); 0
    where a point has fewer than 48 usable frames.  A platform that wanders or rings in the flow
    is not where the stiffness model puts it for the mean load: the tare pose weighs the camera
    more there (:func:`cdpr.analysis.tare.tare_pose`)."""
    q = np.asarray(poses, dtype=np.float64)
    s = len(ranges)
    out = np.zeros((s, 6, 6))
    if q.shape[0] < 2 or s == 0:
        return out
    bits = np.asarray(pose_bits)
    C = np.asarray(camera_cov_of_mean, dtype=np.float64)
    for i, (a, b) in enumerate(ranges):
        x = q[a:b][(bits[a:b] == 0) & np.isfinite(q[a:b]).all(axis=1)]
        # a long window's frames as the means of at most MAX_POSE_BLOCKS blocks (the mean and its
        # long-run covariance are the same; the cost is not that of 1 kHz poses)
        size = -(-x.shape[0] // MAX_POSE_BLOCKS)
        if size > 1:
            nb = x.shape[0] // size
            x = x[: nb * size].reshape(nb, size, 6).mean(axis=1)
        if x.shape[0] < 48 or not np.isfinite(C[i]).all():
            continue
        lr = long_run(x)
        if not np.isfinite(lr.cov_of_mean).all():
            continue
        out[i] = _significant_excess(lr.cov_of_mean, C[i], 1.5 * lr.n / max(lr.bandwidth, 1))
    return out


def _significant_excess(estimate: FloatArray, counted: FloatArray, dof: float) -> FloatArray:
    """The part of the covariance ``estimate`` beyond ``counted`` (both (6, 6)) in the directions
    where it is beyond the estimate's own scatter: in the coordinates where ``counted`` is the
    identity, the eigenvalues above ``1 + 2 sqrt(2 / dof)`` (two standard deviations of a variance
    estimated with ``dof`` degrees of freedom; a Bartlett estimate has about ``1.5 n / bandwidth``,
    Priestley 1981, 6.2.4), less 1."""
    w, V = np.linalg.eigh(0.5 * (counted + counted.T))
    floor = max(float(w.max()), 0.0) * 1e-12
    if floor <= 0:
        return np.zeros_like(counted)
    half = (V * np.sqrt(np.clip(w, floor, None))) @ V.T  # counted^(1/2)
    ihalf = (V / np.sqrt(np.clip(w, floor, None))) @ V.T
    lam, U = np.linalg.eigh(ihalf @ (0.5 * (estimate + estimate.T)) @ ihalf)
    x = np.where(lam > 1.0 + 2.0 * np.sqrt(2.0 / max(dof, 1.0)), lam - 1.0, 0.0)
    return np.asarray(half @ ((U * x) @ U.T) @ half)


def pose_rate_variance(
    pose_t_ns: ArrayLike,
    poses: ArrayLike,
    pose_bad: ArrayLike,
    ranges: list[tuple[int, int]],
    frame_var: ArrayLike,
) -> FloatArray:
    """The variance of the platform's pose rate within each point's frames (s, 6), (m/s)^2 and
    (rad/s)^2: the scatter of the finite differences of consecutive usable frames, less what the
    camera's own noise puts in them (``2 frame_var / dt^2``, frame_var (s, 6) one frame's
    variance), never below 0; NaN with fewer than two differences.

    A platform that rings (a lightly damped mode excited by the flow) is not at rest over a
    point: the window's mean cable wrench carries the mean inertia wrench ``M (v_end -
    v_start) / T``, an error of order 1/T that no zero-frequency spectrum of the tensions sees
    (:func:`cdpr.analysis.stages.window_motion_stage` takes it into σ).  Differences of frames
    alias a motion faster than half the camera's rate (its velocity is then underestimated)."""
    tp = np.asarray(pose_t_ns, dtype=np.int64)
    q = np.asarray(poses, dtype=np.float64)
    bad = np.asarray(pose_bad, dtype=bool)
    s = len(ranges)
    if tp.shape[0] < 2:
        return np.full((s, 6), np.nan)
    dt = np.diff(tp).astype(np.float64) * 1e-9
    dq = np.diff(q, axis=0)
    dq[:, 3:] = (dq[:, 3:] + np.pi) % (2 * np.pi) - np.pi  # an angle through +-pi
    dbad = bad[1:] | bad[:-1] | (dt <= 0)
    v = dq / np.where(dt > 0, dt, 1.0)[:, None]
    nd = dt.shape[0]  # differences k join frames k and k + 1; a window past the last frame has none
    dranges = [(min(i, nd), min(max(i, j - 1), nd)) for i, j in ranges]
    bits = dbad.astype(np.int64)
    vs = point_stats(v, dranges, bits)
    dts = point_stats(dt, dranges, bits).mean[:, 0]
    with np.errstate(invalid="ignore", divide="ignore"):
        noise = 2.0 * np.asarray(frame_var, dtype=np.float64) / dts[:, None] ** 2
        out = np.clip(vs.sd**2 - noise, 0.0, None)
    return np.asarray(np.where(np.isfinite(vs.sd), out, np.nan))


def _input_words(
    st: PointStats,
    ps: PointStats,
    nominal: NDArray[np.bool_],
    short: NDArray[np.bool_],
    nominal_word: str,
) -> list[str]:
    """The flag words of each point's inputs (masked samples and why, no samples, no pose,
    dropped camera frames, a nominal pose covariance, a window too short for its own
    correlation)."""
    words = []
    for i in range(len(nominal)):
        w = []
        if st.n_masked[i]:
            w.append("masked")
            w += mask_words(int(st.masked_bits[i]))
        if st.n_used[i] < 2:
            w.append("no_samples")
        if ps.n_used[i] == 0:
            w.append("no_pose")
        elif ps.n_masked[i]:
            w.append("pose_flagged")
        if nominal[i]:
            w.append(nominal_word)
        if short[i]:
            w.append("window_too_short")
        words.append(";".join(w))
    return words
