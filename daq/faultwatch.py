"""Faults seen in the data while recording: flagged, stuck or noisy load cells and a camera that
lost its markers, each turned into one ``/event`` when it starts and one when it ends.

The recorder's writer hands every batch to :meth:`DataWatch.feed`; readings of ``*tensions``
streams go to a :class:`TensionWatch` per stream, ``*pose`` readings to the marker check.  Events
have ``name = "fault"``, ``source`` (the stream), ``fault`` (the kind below; ``<kind>_end`` when it
clears), ``cable`` for per-cable kinds and ``t_start_ns`` (host time of the first sample concerned):

- ``saturated`` / ``slack`` / ``sensor_fault``: the amplifier's per-cable status bits (1, 2, 4);
- ``stuck``: a cable's raw counts identical for ``stuck_samples`` samples in a row while the
  amplifier reports nothing (a stuck cell is not self-reporting; real counts are never that quiet);
- ``noise_burst``: the robust spread (MAD) of a cable's sample-to-sample count changes over the
  last ``window`` samples above ``noise_factor`` times its running baseline (floor 1 count);
- ``markers_lost``: camera poses flagged unusable (``STATUS_BAD_FRAME``), e.g. no markers in view.

The work per batch is a few numpy reductions over a window of ``window`` samples.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from .mcap_writer import is_frame_batch
from .source import STATUS_BAD_FRAME, Reading

_BITS = ((1, "saturated"), (2, "slack"), (4, "sensor_fault"))
_MISSING = -(1 << 31)


class TensionWatch:
    """Fault detection on one tensions stream (see the module docstring)."""

    def __init__(
        self,
        stream: str,
        emit: Callable[..., None],
        *,
        window: int = 40,
        stuck_samples: int = 25,
        noise_factor: float = 4.0,
        noise_every: int = 8,
    ) -> None:
        self.stream = stream
        self.emit = emit
        self.window = int(window)
        self.stuck_samples = int(stuck_samples)
        self.noise_factor = float(noise_factor)
        self.noise_every = int(noise_every)
        self.cables: list[str] = []
        self._raw_keys: list[str] = []
        self._status_keys: list[str] = []
        self._hist: np.ndarray | None = None  # last `window` raw counts (float, NaN missing)
        self._run: np.ndarray | None = None  # identical-count run length per cable
        self._baseline: np.ndarray | None = None
        self._last_raw: np.ndarray | None = None
        self._run_t0 = np.zeros(0, np.int64)
        self._seen = 0
        self.active: dict[tuple[str, str], int] = {}  # (kind, cable) -> t_start_ns
        self.recent_T_N: np.ndarray = np.zeros((0, 0))  # the last `keep` tension samples, N
        self.recent_t_ns: np.ndarray = np.zeros(0, np.int64)
        self.keep = 512

    def _setup(self, values: Any) -> None:
        self.cables = [k[4:-7] for k in values if k.startswith("raw_") and k.endswith("_counts")]
        self._raw_keys = [f"raw_{c}_counts" for c in self.cables]
        self._status_keys = [f"status_{c}" for c in self.cables]
        n = len(self.cables)
        self._hist = np.full((0, n), np.nan)
        self._run = np.zeros(n, np.int64)
        self._run_t0 = np.zeros(n, np.int64)
        self._baseline = np.full(n, np.nan)

    def _edge(self, kind: str, cable: str, on: bool, t_ns: int) -> None:
        key = (kind, cable)
        if on and key not in self.active:
            self.active[key] = t_ns
            self.emit(
                f"{self.stream}: cable {cable} {kind.replace('_', ' ')}",
                "error",
                name="fault",
                source=self.stream,
                fault=kind,
                cable=cable,
                t_start_ns=t_ns,
            )
        elif not on and key in self.active:
            t0 = self.active.pop(key)
            self.emit(
                f"{self.stream}: cable {cable} {kind.replace('_', ' ')} ended after "
                f"{(t_ns - t0) / 1e9:.2f} s",
                "warning",
                name="fault",
                source=self.stream,
                fault=f"{kind}_end",
                cable=cable,
                t_start_ns=t0,
            )

    def _track(
        self, kind: str, cable: str, on: np.ndarray, t: np.ndarray, t_on: int | None = None
    ) -> None:
        """Events for one cable's condition ``on`` over the samples at times ``t``: it starts at
        its first sample (or ``t_on``: a run detected late), ends at the last."""
        if on.any():
            if (kind, cable) not in self.active:
                first = int(np.argmax(on))
                self._edge(kind, cable, True, int(t[first]) if t_on is None else t_on)
            if not on[-1]:
                self._edge(kind, cable, False, int(t[-1]))
        elif (kind, cable) in self.active:
            self._edge(kind, cable, False, int(t[0]))

    def _concerned(self, kind: str, on: np.ndarray) -> list[int]:
        """Cables with ``kind`` on in ``on`` (rows x cables) or active: the only ones to look at."""
        cols = set(np.flatnonzero(on.any(axis=0)).tolist())
        cols |= {self.cables.index(c) for k, c in self.active if k == kind}
        return sorted(cols)

    def feed(self, readings: Sequence[Reading]) -> None:
        if not readings:
            return
        if self._hist is None:
            self._setup(readings[0].values)
        assert self._hist is not None and self._run is not None and self._baseline is not None
        if not self.cables:
            return
        raw = np.array(
            [[r.values.get(k, _MISSING) for k in self._raw_keys] for r in readings], np.float64
        )
        raw[raw == _MISSING] = np.nan
        status = np.array(
            [[r.values.get(k, 0) or 0 for k in self._status_keys] for r in readings], np.int64
        )
        t = np.array([r.t_ns for r in readings], np.int64)
        T = np.array(
            [[r.values.get(f"T_{c}_N", np.nan) for c in self.cables] for r in readings], np.float64
        )
        if self.recent_T_N.shape[1:] != T.shape[1:]:
            self.recent_T_N = T[:0]
        self.recent_T_N = np.vstack([self.recent_T_N, T])[-self.keep :]
        self.recent_t_ns = np.concatenate([self.recent_t_ns, t])[-self.keep :]
        # status bits, per cable: a flag that starts (and maybe ends) in this batch
        any_flag = status != 0
        for bit, kind in _BITS:
            on = (status & bit) != 0
            for j in self._concerned(kind, on):
                self._track(kind, self.cables[j], on[:, j], t)
        # stuck: run length of identical counts (not when missing or self-reported), vectorised
        prev = self._last_raw if self._last_raw is not None else raw[:1] * np.nan
        self._last_raw = raw[-1:]
        same = (np.diff(np.vstack([prev, raw]), axis=0) == 0) & ~any_flag
        idx = np.arange(len(raw))[:, None]
        last_reset = np.maximum.accumulate(np.where(same, -1, idx), axis=0)
        run = np.where(last_reset >= 0, idx - last_reset, self._run[None, :] + idx + 1)
        stuck = run >= self.stuck_samples
        n_rows = len(raw)
        for j in self._concerned("stuck", stuck):
            c = self.cables[j]
            col = stuck[:, j]
            t_on = None
            if col.any():  # the run began at its first repeated sample, maybe in a past batch
                f = int(np.argmax(col))
                k = f - int(run[f, j]) + 1
                t_on = int(t[k]) if k >= 0 else int(self._run_t0[j])
            self._track("stuck", c, col, t, t_on=t_on)
        # where each current run began (for a run found stuck in a later batch)
        k = n_rows - run[-1]
        here = (run[-1] > 0) & (k >= 0)
        self._run_t0[here] = t[k[here]]
        self._run = run[-1]
        # noise: MAD of first differences over the window against a slow baseline
        # a flagged or stuck sample says nothing about the noise
        quiet = np.where(any_flag | stuck, np.nan, raw)
        self._hist = np.vstack([self._hist, quiet])[-(self.window + 1) :]
        seen0 = self._seen
        self._seen += len(raw)
        # the noise verdict every `noise_every` samples (two medians over the window)
        if len(self._hist) <= self.window // 2 or seen0 // self.noise_every == (
            self._seen // self.noise_every
        ):
            return
        d = np.diff(self._hist, axis=0)
        with warnings.catch_warnings():  # a cable flagged the whole window: all NaN, no verdict
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(d, axis=0)
            spread = np.maximum(1.4826 * np.nanmedian(np.abs(d - med), axis=0), 1.0)
        base = self._baseline
        ready = self._seen >= 2 * self.window
        burst = (
            ready & np.isfinite(base) & (spread > self.noise_factor * np.nan_to_num(base, nan=1))
        )
        for j in self._concerned("noise_burst", burst[None, :]):
            self._track("noise_burst", self.cables[j], burst[j : j + 1], t[:1])
        # the baseline follows slow changes only, never a burst
        calm = np.isfinite(spread) & ~burst
        base[calm] = np.where(np.isfinite(base[calm]), 0.95 * base[calm] + 0.05 * spread[calm],
                              spread[calm])  # fmt: skip


class DataWatch:
    """Routes the recorder's batches to the watches by stream name (see the module docstring)."""

    def __init__(self, emit: Callable[..., None]) -> None:
        self.emit = emit
        self._tensions: dict[str, TensionWatch] = {}
        self._markers_lost: dict[str, int] = {}

    def recent_tensions(self) -> tuple[list[str], np.ndarray, np.ndarray]:
        """The cables, times (k,) ns and tensions (k, m) N of the latest samples of the first
        tensions stream (empty before any)."""
        for w in self._tensions.values():
            return list(w.cables), w.recent_t_ns, w.recent_T_N
        return [], np.zeros(0, np.int64), np.zeros((0, 0))

    def feed(self, batch: Sequence[Reading]) -> None:
        others = getattr(batch, "others", None)
        readings: Sequence[Reading] = [r for _, r in others] if is_frame_batch(batch) else batch
        ten: dict[str, list[Reading]] = {}
        for r in readings:
            s = r.stream
            if s.endswith("tensions"):
                ten.setdefault(s, []).append(r)
            elif s.endswith("pose"):
                self._pose(r)
        for s, rs in ten.items():
            w = self._tensions.get(s)
            if w is None:
                w = self._tensions[s] = TensionWatch(s, self.emit)
            w.feed(rs)

    def _pose(self, r: Reading) -> None:
        bad = bool(r.status & STATUS_BAD_FRAME)
        s = r.stream
        if bad and s not in self._markers_lost:
            self._markers_lost[s] = r.t_ns
            n = r.values.get("n_points", 0)
            self.emit(
                f"{s}: camera pose unusable (markers lost, {n} points)",
                "error",
                name="fault",
                source=s,
                fault="markers_lost",
                t_start_ns=r.t_ns,
            )
        elif not bad and s in self._markers_lost:
            t0 = self._markers_lost.pop(s)
            self.emit(
                f"{s}: markers found again after {(r.t_ns - t0) / 1e9:.2f} s",
                "warning",
                name="fault",
                source=s,
                fault="markers_lost_end",
                t_start_ns=t0,
            )
