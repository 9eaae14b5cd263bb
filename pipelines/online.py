"""The on-line reduction: ``cdpr analyze``'s reduction core on the samples of the session so far.

While a test point is open and steady, :class:`OnlineReduction` gives the point's wrench and
coefficients with σ at least once a second (the live server drives it: ``/online``, the terminal
view); when the point has ended (and a sample past its end has arrived), its result over exactly
the point's window is marked ``final`` and the live server records it as an ``online_result``
event on ``/events``, which ``cdpr analyze`` compares with its final values
(:mod:`cdpr.pipelines.online_compare`).

The session's samples (tensions with their status and counter, the camera's poses with their
covariance, the tunnel conditions, the test-point events) are kept inside the test points (and
the last few seconds), in bounded buffers; every update builds the same :class:`RunData` that
``cdpr analyze`` reads from a run file and calls :func:`reduce_session`, the ONE function
through which it runs the reduction core (``cdpr analyze``'s ``reduce_run``).  So the on-line
values are the core's with what is known so far: weight tares and the weight model from the
wind-off points already recorded, windage from the windage points already recorded (else the
model), zero drift held from the last zero (flag ``no_closing_zero``), q from the tunnel stream,
body and wind axes at the model's moment reference point.  What the live session cannot know is
said by flags, never filled in: no virtual-rig truth file (a run without a camera is reduced at
the rig's reference pose, flag ``no_pose_stream``); the spectrum check's flags are left out (only
the samples inside the points are kept, so the check's estimate of the run's sample rate is not
the recording's).
"""

from __future__ import annotations

import math
import operator
import threading
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from cdpr.analysis.conventions import COEFFICIENTS, WRENCH_COLUMNS
from cdpr.analysis.rig import Rig

from .analyze import AnalyzeOptions, reduce_run
from .run_arrays import RunData, camera_poses, tension_arrays, tunnel_on

ONLINE_VALUE_COLUMNS: tuple[str, ...] = (
    "airspeed_mps", "density_kgpm3", "q_Pa", "aoa_rad", "sideslip_rad",
    *WRENCH_COLUMNS, *(f"sd_{c}" for c in WRENCH_COLUMNS),
    "fx_B_N", "fy_B_N", "fz_B_N", "mx_B_Nm", "my_B_Nm", "mz_B_Nm", "drag_N", "side_N", "lift_N",
    *COEFFICIENTS, *(f"sd_{c}" for c in COEFFICIENTS),
)  # fmt: skip
"""The per-point values an on-line result carries (the names of ``points.csv``)."""

LIVE_PATH = Path("<live session>")
"""What the on-line reduction's RunData names as its file."""
SPECTRUM_FLAGS = frozenset({"too_few_periods", "spectrum_peak_near_mode", "no_modes"})


def reduce_session(run: RunData, opts: AnalyzeOptions) -> pd.DataFrame:
    """The per-point table of the session so far through the reduction core: ``cdpr analyze``'s
    own :func:`cdpr.pipelines.analyze.reduce_run` on the live :class:`RunData`.  The one call into
    the core of the on-line reduction."""
    df, _ = reduce_run(run, opts)
    return df


class _Columns:
    """Rows of fixed width appended to preallocated arrays (doubling), kept in time order."""

    def __init__(self, widths: Mapping[str, tuple[int, Any]]) -> None:
        self.widths = dict(widths)
        self.n = 0
        self.cols = {k: np.empty((64, w), dt) for k, (w, dt) in self.widths.items()}

    def extend(self, rows: Mapping[str, list[Any]]) -> None:
        k = len(rows["t"])
        if not k:
            return
        cap = len(self.cols["t"])
        if self.n + k > cap:
            new = max(2 * cap, self.n + k)
            for name, a in self.cols.items():
                b = np.empty((new, a.shape[1]), a.dtype)
                b[: self.n] = a[: self.n]
                self.cols[name] = b
        for name, vals in rows.items():
            self.cols[name][self.n : self.n + k] = np.asarray(vals, self.cols[name].dtype).reshape(
                k, -1
            )
        self.n += k

    def view(self, name: str) -> Any:
        return self.cols[name][: self.n]

    def keep(self, mask: Any) -> None:
        idx = np.flatnonzero(mask)
        for a in self.cols.values():
            a[: len(idx)] = a[idx]
        self.n = len(idx)


class OnlineReduction:
    """The on-line reduction of a recording session (see the module docstring); the live server
    calls :meth:`feed` with every written batch and :meth:`update` at least once a second.

    rig: the run's rig; opts: the analysis options (geometry, corrections and the test section
    from the test matrix, as ``cdpr analyze --matrix`` takes them); steady_window_s, steady_sd_N:
    the live view's steadiness rule (largest σ over the cables of the last window below the
    limit); keep_s: samples outside the test points kept this long; max_samples: the most tension
    samples kept (the oldest dropped beyond, flag ``online_samples_capped``); wait_after_end_s: an
    ended point waits this long (at most) for a sample past its end before it is reduced.
    """

    def __init__(
        self,
        rig: Rig,
        opts: AnalyzeOptions,
        *,
        steady_window_s: float = 1.0,
        steady_sd_N: float = 0.5,
        keep_s: float = 5.0,
        max_samples: int = 2_000_000,
        wait_after_end_s: float = 2.0,
    ) -> None:
        self.rig = rig
        self.opts = opts
        self.cables = list(rig.cable_names)
        m = len(self.cables)
        self.steady_window_ns = int(steady_window_s * 1e9)
        self.steady_sd_N = float(steady_sd_N)
        self.keep_ns = int(keep_s * 1e9)
        self.max_samples = int(max_samples)
        self.wait_after_end_s = float(wait_after_end_s)
        self._lock = threading.Lock()
        self._feed_lock = threading.Lock()
        self._chunks: list[tuple[Any, ...]] = []
        self._seq_ok = True
        self._tens = _Columns({"t": (1, np.int64), "T": (m, np.float64), "st": (1, np.int64),
                               "seq": (1, np.int64)})  # fmt: skip
        self._tun = _Columns({"t": (1, np.int64), "v": (5, np.float64)})
        self._pose = _Columns({"t": (1, np.int64), "v": (3 + 4 + 36 + 2, np.float64)})
        self._events: list[tuple[int, dict[str, Any]]] = []
        self._open: tuple[str, int] | None = None
        self._ended: list[tuple[str, int, int, float]] = []
        self._capped_before_ns: int | None = None
        self._cols_T = [f"T_{c}_N" for c in self.cables]
        self._cols_st = [f"status_{c}" for c in self.cables]
        self._get_T = operator.itemgetter(*self._cols_T)
        self._get_S = operator.itemgetter(*self._cols_st)

    # feed (publisher thread) -----------------------------------------------------------------
    def feed(self, readings: Sequence[Any]) -> None:
        """Keep what the reduction needs of a written batch (called by the live server's
        publisher thread for every batch: a few dict look-ups per reading, the arrays are made by
        :meth:`update`)."""
        t: list[int] = []
        st: list[int] = []
        T: list[Any] = []
        S: list[Any] = []
        seq: list[Any] = []
        pose: list[list[Any]] = []
        tun: list[list[Any]] = []
        get_T, get_S = self._get_T, self._get_S
        for r in readings:
            stream = r.stream
            v = r.values
            if stream == "tensions" or stream.endswith("/tensions"):
                try:
                    T.append(get_T(v))
                    S.append(get_S(v))
                except KeyError:  # a sample without some field: NaN / no status there
                    T.append(tuple(v.get(c) for c in self._cols_T))
                    S.append(tuple(v.get(c) for c in self._cols_st))
                t.append(r.t_ns)
                st.append(r.status)
                seq.append(v.get("seq"))
            elif stream == "pose" or stream.endswith("/pose"):
                p, q, c = v.get("position_O_m"), v.get("quaternion_wxyz"), v.get("covariance")
                row: list[Any] = [r.t_ns]
                row += [_num(x) for x in p] if p is not None and len(p) == 3 else [math.nan] * 3
                row += [_num(x) for x in q] if q is not None and len(q) == 4 else [math.nan] * 4
                has = c is not None and len(c) == 36
                row += [_num(x) for x in c] if has else [math.nan] * 36
                row += [1.0 if has else 0.0, float(r.status or 0)]
                pose.append(row)
            elif stream == "tunnel" or stream.endswith("/tunnel"):
                tun.append(
                    [r.t_ns, *(_num(v.get(k)) for k in ("airspeed_mps", "density_kgpm3",
                     "static_pressure_Pa", "temperature_K", "relative_humidity"))]
                )  # fmt: skip
            elif v.get("name") == "test_point" and stream.rsplit("/", 1)[-1].startswith("event"):
                self._on_event(r.t_ns, dict(v))
        if t or pose or tun:
            with self._feed_lock:  # one append per batch; update() takes the chunks under it
                self._chunks.append((t, st, T, S, seq, pose, tun))

    def _on_event(self, t_ns: int, fields: dict[str, Any]) -> None:
        with self._lock:
            self._events.append((t_ns, fields))
            label = str(fields.get("point", ""))
            if fields.get("phase") == "start":
                if self._open is not None:  # a point never ended: reduced up to here
                    self._ended.append((self._open[0], self._open[1], t_ns - 1, time.monotonic()))
                self._open = (label, t_ns)
            elif fields.get("phase") == "end" and self._open is not None and self._open[0] == label:
                self._ended.append((label, self._open[1], t_ns, time.monotonic()))
                self._open = None

    def pending(self) -> int:
        return len(self._ended)

    # update (on-line thread) -----------------------------------------------------------------
    def _flush_rows(self) -> None:
        """The chunks :meth:`feed` kept, into the arrays (the tensions' status words OR-ed over
        the cables and the reading, as ``cdpr analyze`` reads them)."""
        with self._feed_lock:
            chunks, self._chunks = self._chunks, []
        for t, st, T, S, seq, pose, tun in chunks:
            if t:
                Ta = np.array(T, dtype=np.float64).reshape(len(t), -1)
                Sa = np.nan_to_num(np.array(S, dtype=np.float64).reshape(len(t), -1))
                words = np.bitwise_or.reduce(Sa.astype(np.int64), axis=1) | np.array(st, np.int64)
                if any(q is None for q in seq):
                    self._seq_ok = False
                seq_a = [0 if q is None else int(q) for q in seq]
                self._tens.extend({"t": t, "T": Ta, "st": words, "seq": seq_a})
            for rows_, buf in ((pose, self._pose), (tun, self._tun)):
                if rows_:
                    buf.extend({"t": [r[0] for r in rows_], "v": [r[1:] for r in rows_]})

    def _compact(self) -> None:
        """Keep the samples inside the test points (and the last ``keep_s``), at most
        ``max_samples``."""
        starts = [e[0] for e in self._events if e[1].get("phase") == "start"]
        ends = [e[0] for e in self._events if e[1].get("phase") == "end"]
        for buf, cap, slack in ((self._tens, self.max_samples, 1), (self._pose, None, 1),
                                (self._tun, None, 1)):  # fmt: skip
            if buf.n < 4096:
                continue
            t = buf.view("t")[:, 0]
            keep = t >= t[-1] - self.keep_ns
            for a in starts:
                # a slower stream keeps its sample before and after the point (interpolation)
                b = min((e for e in ends if e >= a), default=t[-1])
                i, j = np.searchsorted(t, [a, b], side="left")
                keep[max(i - slack, 0) : j + slack + 1] = True
            if cap is not None and keep.sum() > cap:
                cut = np.flatnonzero(keep)[-cap]
                self._capped_before_ns = int(t[cut])
                keep[:cut] = False
            if not keep.all():
                buf.keep(keep)

    def _run_data(self) -> RunData:
        """The session so far as ``cdpr analyze`` reads a run file: the same tension arrays,
        tunnel conditions and camera poses (:mod:`cdpr.pipelines.run_arrays`)."""
        tb = self._tens
        seq = tb.view("seq")[:, 0].copy() if self._seq_ok else None
        t, T, bits, seq, clock = tension_arrays(
            tb.view("t")[:, 0].copy(), tb.view("T").copy(), tb.view("st")[:, 0].copy(), seq
        )
        tv = self._tun.view("v")
        tunnel, pT, rh = tunnel_on(t, self._tun.view("t")[:, 0], *(tv[:, k] for k in range(5)))
        rig = self.rig
        events = sorted(self._events, key=lambda e: e[0])
        pv = self._pose.view("v")
        if len(pv):
            q6, cov, bad = camera_poses(pv[:, :3], pv[:, 3:7], pv[:, 7:43].reshape(-1, 6, 6),
                                        pv[:, 44])  # fmt: skip
            if (~bad).sum() >= 2:
                src = "camera (/pose stream)" + ("" if cov is not None else ", no covariance")
                return RunData(
                    LIVE_PATH, rig, t, T, bits, tunnel, self._pose.view("t")[:, 0].copy(), q6, cov,
                    bad, src, events, None, True, pT, rh, None, clock, seq,
                )  # fmt: skip
        ref = np.concatenate([rig.reference_position_O_m, rig.reference_euler_rad])
        return RunData(
            LIVE_PATH, rig, t, T, bits, tunnel, t.copy(), np.tile(ref, (len(t), 1)), None,
            np.zeros(len(t), bool), "rig reference pose (no pose stream)", events, None, False,
            pT, rh, None, clock, seq,
        )  # fmt: skip

    def _steadiness(self) -> tuple[bool, float]:
        tb = self._tens
        if tb.n < 2:
            return False, math.nan
        t = tb.view("t")[:, 0]
        win = tb.view("T")[t >= t[-1] - self.steady_window_ns]
        win = win[np.isfinite(win).all(axis=1)]
        if len(win) < 2:
            return False, math.nan
        sd = float(np.max(np.std(win, axis=0)))
        return sd < self.steady_sd_N, sd

    def update(
        self, final: bool = False
    ) -> tuple[Mapping[str, Any] | None, list[Mapping[str, Any]]]:
        with self._lock:
            self._flush_rows()
            self._compact()
            if self._tens.n < 3:
                return None, []
            t_last = int(self._tens.view("t")[-1, 0])
            # an ended point waits for a sample past its end in every stream it interpolates
            # (tensions, tunnel, pose), as the final analysis has them, or for the time limit
            seen = min(int(b.view("t")[-1, 0]) for b in (self._tens, self._tun, self._pose) if b.n)
            now = time.monotonic()
            ready = [
                e for e in self._ended
                if final or seen > e[2] or now - e[3] > self.wait_after_end_s
            ]  # fmt: skip
            for e in ready:
                self._ended.remove(e)
            open_ = self._open
            steady, sd = self._steadiness()
            if not ready and open_ is None:
                return None, []
            if not ready and not steady:
                assert open_ is not None
                return {
                    "point": open_[0], "t_ns": t_last, "steady": False, "max_sd_N": sd,
                    "final": False, "n_samples": 0,
                }, []  # fmt: skip
            run = self._run_data()
            capped = self._capped_before_ns
        df = reduce_session(run, self.opts)
        got = [self._result(df, label, t0, run, True, t1) for label, t0, t1, _ in ready]
        results = [r for r in got if r is not None]
        msg = None
        if open_ is not None and steady:
            msg = self._result(df, open_[0], open_[1], run, False, t_last)
            if msg is not None:
                msg["max_sd_N"] = sd
        for res in [*results, *([msg] if msg else [])]:
            if capped is not None and res["start_ns"] < capped:
                res["flags"] = ";".join(filter(None, [res["flags"], "online_samples_capped"]))
        return msg, results

    def _result(
        self, df: pd.DataFrame, label: str, t0: int, run: RunData, final: bool, t_ns: int
    ) -> dict[str, Any] | None:
        rows = df[df["point"] == label]
        if rows.empty:  # no samples of the point were kept: nothing to say
            return None
        if len(rows) > 1:  # the same label twice: the one that started nearest t0
            rows = rows.iloc[[int(np.argmin(np.abs(rows["start_ns"].to_numpy() - t0)))]]
        r = rows.iloc[0]
        flags = [w for w in str(r["flags"]).split(";") if w and w not in SPECTRUM_FLAGS]
        if not final:
            flags = [w for w in flags if w != "no_end_event"]
        out: dict[str, Any] = {
            "point": label,
            "kind": str(r["kind"]),
            "t_ns": int(t_ns),
            "start_ns": int(r["start_ns"]),
            "stop_ns": int(r["stop_ns"]),
            "n_samples": int(r["n_samples"]),
            "n_masked": int(r["n_masked"]),
            "steady": True,
            "final": final,
            "corrections": "as cdpr analyze --matrix (zero drift held from the last zero)"
            if self.opts.corrections
            else "none (balance values, as cdpr analyze without --matrix)",
            "pose_source": run.pose_source,
            "flags": ";".join(flags),
        }
        for c in ONLINE_VALUE_COLUMNS:
            if c in r:
                v = float(r[c])
                out[c] = v if math.isfinite(v) else None
        return out


def _num(x: Any) -> float:
    return float(x) if isinstance(x, int | float) and not isinstance(x, bool) else math.nan


def online_options(matrix_file: str | None) -> AnalyzeOptions:
    """The on-line reduction's options: with a test matrix, as ``cdpr analyze --matrix`` takes
    them (the model geometry, the corrections, the test section); without one, the balance
    values (no geometry: no coefficients)."""
    if matrix_file is None:
        return AnalyzeOptions()
    from .campaign import load_test_matrix

    m = load_test_matrix(matrix_file)
    return AnalyzeOptions(
        geometry=m.model,
        corrections=True,
        tunnel=m.tunnel,
        matrix_file=str(matrix_file),
        instruments=m.instruments,
    )
