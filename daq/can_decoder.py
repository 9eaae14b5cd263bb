"""Load-cell samples from CAN frames: one decoder, :meth:`LoadCellDecoder.decode_frames`, over frame
columns (:class:`~cdpr.daq.can_frames.FrameColumns`), used by the live CAN driver
(:mod:`cdpr.daq.can_source`), log replay (:mod:`cdpr.daq.replay`) and ``cdpr import``
(:mod:`cdpr.daq.can_import`) alike.

The DBC (its naming, and the signals of frames unpacked with it): :mod:`cdpr.daq.can_dbc`.

The ``tensions`` stream: one sample per counter value: ``T_<cable>_N``, ``raw_<cable>_counts``,
``status_<cable>`` (DBC bits: 1 saturated, 2 slack, 4 fault), ``counter`` (0..255), ``seq``
(unwrapped counter) and ``t_bus_ns``, with the time (``t_ns``) and bus time of the sample's first
frame.

The rules, frame by frame in the order they came (what :meth:`decode_frames` computes for a whole
block at once with numpy; only irregular stretches, a frame repeated within one counter value,
go through a loop):

- a load-cell frame is one of the DBC's ids with the DBC's extended flag, neither an error nor a
  remote frame; any other frame is not looked at;
- a load-cell frame of another length than the DBC's, or that cantools cannot decode, is a **bad
  frame**: counted (:attr:`LoadCellDecoder.bad`) and flagged in the frame mask the decoder returns;
- a frame whose counter differs from the open sample's closes that sample; a sample closes when it
  has every frame of the DBC once; a frame already in the open sample is a bad frame (kept: the
  first); a bad frame flags the sample open at the time, else the next one, ``STATUS_BAD_FRAME``;
- a sample closed with a frame missing has NaN tensions and ``raw = -2**31`` for the missing
  channels and ``STATUS_GAP`` (:attr:`LoadCellDecoder.partial` counts them);
- counter gaps count as lost samples: the gap is what the 8-bit counter says, modulo 256 (a jump
  from 10 to 13 is 2 lost, from 250 to 3 is 8 lost, the same value again 255).  Whole wraps
  cannot be seen in the counter, and are never guessed from host time: a host-time gap between
  two samples longer than one wrap (256 samples, 1.28 s at 200 Hz) is a **pause** (a sender or
  reader that stopped, or an outage of unknown size), counted in :attr:`LoadCellDecoder.n_pauses`
  with its start and duration kept in :attr:`LoadCellDecoder.pauses`.

A sample still open at the end of a block waits for the next block (its frames are kept);
:meth:`LoadCellDecoder.flush` closes it at the end of the data, :meth:`LoadCellDecoder.reset`
drops it after a bus reopen.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cdpr.analysis.conventions import status_from_channel_bits
from cdpr.analysis.errors import ConfigError

from .can_dbc import (
    DEFAULT_DBC,
    LoadCellDbc,
    default_cable_names,
    load_dbc,
    n_counts_channels,
)
from .can_frames import FrameColumns, concat_frames, empty_frames
from .loadcell import RAW_MISSING_COUNTS, Calibration, calibration_from_settings
from .source import (
    STATUS_BAD_FRAME,
    STATUS_GAP,
    FieldDescription,
    Reading,
    StreamDescription,
)

log = logging.getLogger(__name__)

#: pauses kept in :attr:`LoadCellDecoder.pauses` (the count goes on)
MAX_PAUSES = 1000


@dataclass
class Samples:
    """Samples of the ``tensions`` stream as columns, and what the decoder saw in the frames.

    t_ns: (k,) int64 sample times; columns: the stream's fields in order (``T_<cable>_N`` float64,
    ``raw_<cable>_counts``, ``status_<cable>``, ``counter``, ``seq``, ``t_bus_ns`` int64); status:
    (k,) int64; done_at: (k,) int64, the index of the block's frame whose arrival closed each sample
    (its last frame, or the next sample's first; the block's length for :meth:`flush`); bad: (n,)
    bool over the block's frames, the bad load-cell frames.
    """

    t_ns: np.ndarray
    columns: dict[str, np.ndarray]
    status: np.ndarray
    done_at: np.ndarray
    bad: np.ndarray

    def __len__(self) -> int:
        return len(self.t_ns)

    def take(self, index: Any) -> Samples:
        """Samples ``index`` (the frame mask unchanged)."""
        return Samples(
            self.t_ns[index],
            {k: v[index] for k, v in self.columns.items()},
            self.status[index],
            self.done_at[index],
            self.bad,
        )

    def readings(self, stream: str = "tensions") -> list[Reading]:
        """One :class:`~cdpr.daq.source.Reading` per sample (the live path)."""
        names = list(self.columns)
        rows = zip(*(self.columns[k].tolist() for k in names), strict=True)
        return [
            Reading(stream, t, dict(zip(names, row, strict=True)), s)
            for t, s, row in zip(self.t_ns.tolist(), self.status.tolist(), rows, strict=True)
        ]


class LoadCellDecoder:
    """Decodes load-cell frames (DBC naming in the module docstring) into ``tensions`` samples.

    db: a cantools database; cables: one name per channel, channel k (1-based) -> ``cables[k-1]``;
    calibration: per-channel offsets and gains (len(cables) channels); rate_hz: the amplifier's
    sample rate (0: unknown, no pause detection).
    """

    def __init__(
        self, db: Any, cables: Sequence[str], calibration: Calibration, rate_hz: float = 0.0
    ) -> None:
        self.db = db
        self.rate_hz = float(rate_hz)
        self.cables = list(cables)
        self.calibration = calibration
        n = len(self.cables)
        self.n = n
        self.dbc = LoadCellDbc(db, self.cables)
        self.frame_ids = self.dbc.frame_ids
        self._entries = self.dbc.entries
        self._keys_T = [f"T_{c}_N" for c in self.cables]
        self._keys_raw = [f"raw_{c}_counts" for c in self.cables]
        self._keys_status = [f"status_{c}" for c in self.cables]
        self.lost = 0
        self.partial = 0
        self.bad = 0
        #: host-time gaps between two samples longer than a counter wrap: ``(t_ns, duration_ns)``
        #: of the last sample before each (at most MAX_PAUSES kept; ``n_pauses`` counts them all)
        self.pauses: list[tuple[int, int]] = []
        self.n_pauses = 0
        #: one wrap of the 8-bit counter (ns); 0: unknown rate, no pause detection
        self.wrap_ns = int(round(256e9 / self.rate_hz)) if self.rate_hz > 0 else 0
        self._last_counter: int | None = None
        self._last_t_ns = 0
        self._seq = -1
        # the open sample: its frames (kept until it closes), their times; a bad frame seen that
        # flags the open sample, else the next
        self._open = empty_frames()
        self._open_t = np.empty(0, np.int64)
        self._bad_mark = False

    @property
    def frames_per_sample(self) -> int:
        return len(self.frame_ids)

    @property
    def max_frame_bytes(self) -> int:
        return self.dbc.max_frame_bytes

    @property
    def extended_ids(self) -> bool:
        return self.dbc.extended_ids

    def reset(self) -> None:
        """Drop the open sample (after a bus reopen).  The counter history stays: the device kept
        counting, so the gap over the outage is counted as lost samples."""
        self._open = empty_frames()
        self._open_t = np.empty(0, np.int64)
        self._bad_mark = False

    def describe(self, rate_hz: float) -> StreamDescription:
        fields: dict[str, FieldDescription] = {}
        for c in self.cables:
            fields[f"T_{c}_N"] = FieldDescription("N")
        for c in self.cables:
            fields[f"raw_{c}_counts"] = FieldDescription("counts", "int64")
        for c in self.cables:
            fields[f"status_{c}"] = FieldDescription("", "int64")
        fields["counter"] = FieldDescription("", "int64")
        fields["seq"] = FieldDescription("", "int64")
        fields["t_bus_ns"] = FieldDescription("ns", "int64")
        return StreamDescription(
            fields,
            rate_hz,
            "cable tensions (N) and raw counts per cable; raw_* = -2**31 and T = NaN when missing",
        )

    # --- the one decoding path --------------------------------------------------------------
    def decode_frames(self, frames: FrameColumns, t_ns: Any) -> Samples:
        """Feed a block of frames (any frames, in the order they came; ``t_ns`` (n,) their times:
        host reception, or log time); returns the samples they close (see the module docstring)."""
        n = len(frames)
        t_ns = np.asarray(t_ns, np.int64)
        lc, k, bad_len = self.dbc.load_cell_frames(frames)
        bad = np.zeros(n, bool)
        bad[lc[bad_len]] = True
        good, k = lc[~bad_len], k[~bad_len]
        # the open sample's frames first (positions -n_open .. -1), then the block's
        op = self._open
        n_open = len(op)
        w = max(op.data.shape[1], frames.data.shape[1])
        data = np.zeros((n_open + len(good), w), np.uint8)
        data[:n_open, : op.data.shape[1]] = op.data
        data[n_open:, : frames.data.shape[1]] = frames.data[good]
        length = np.concatenate([op.length, frames.length[good]])
        k = np.concatenate([self.dbc.fid_index(op.arbitration_id), k])
        counter, groups, undecodable = self.dbc.signals(data, length, k)
        if undecodable.any():  # cantools could not: bad frames, and the rest again
            bad[good[undecodable[n_open:]]] = True
            keep = ~undecodable
            good, data, length, k = good[keep[n_open:]], data[keep], length[keep], k[keep]
            counter, groups, _ = self.dbc.signals(data, length, k)
        self.bad += int(bad.sum())
        pos = np.concatenate([np.arange(-n_open, 0), good]).astype(np.int64)
        t_all = np.concatenate([self._open_t, t_ns[good]])
        tb_all = np.concatenate([op.t_bus_ns, frames.t_bus_ns[good]])
        bad_pos = np.flatnonzero(bad).astype(np.float64)
        if self._bad_mark:  # left by the previous block: after the open frames, before the block
            bad_pos = np.concatenate([[-0.5], bad_pos])
        first, last, complete, dup = self._group(k, counter)
        s = len(first)
        is_open = s > 0 and not bool(complete[-1])  # the last sample waits for more frames
        k_closed = s - int(is_open)
        nxt = np.append(pos[first[1:]], np.iinfo(np.int64).max)
        close = np.where(complete, pos[last], nxt)
        marks = self._marks(pos[first].astype(np.float64), close.astype(np.float64), bad_pos, dup)
        out = self._samples(
            counter, k, groups, first, k_closed, complete[:k_closed], marks[:k_closed], t_all,
            tb_all, close[:k_closed], bad,
        )  # fmt: skip
        if is_open:  # keep its frames (the first of each id) and its mark for the next block
            i0 = int(first[-1])
            _, keep_i = np.unique(k[i0:], return_index=True)
            rows = pos[i0 + np.sort(keep_i)]
            old = rows < 0
            self._open = concat_frames([op.take(rows[old] + n_open), frames.take(rows[~old])])
            self._open_t = t_all[i0 + np.sort(keep_i)]
            self._bad_mark = bool(marks[s - 1])
        else:
            self._open = empty_frames()
            self._open_t = np.empty(0, np.int64)
            self._bad_mark = bool(marks[s])
        return out

    def flush(self, n_frames: int = 0) -> Samples:
        """Close the open sample at the end of the data (a partial sample, ``done_at`` =
        ``n_frames``), if there is one."""
        op = self._open
        k = self.dbc.fid_index(op.arbitration_id)
        counter, groups, _ = self.dbc.signals(op.data, op.length, k)
        one = np.zeros(int(len(op) > 0), np.int64)
        out = self._samples(
            counter, k, groups, one, len(one), one.astype(bool),
            np.full(len(one), self._bad_mark), self._open_t, op.t_bus_ns, one + n_frames,
            np.zeros(n_frames, bool),
        )  # fmt: skip
        self.reset()
        return out

    # --- the steps ----------------------------------------------------------------------------
    def _group(
        self, fid: np.ndarray, counter: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The samples of a sequence of good load-cell frames: ``(first, last, complete,
        dup_marks)``: each sample's first and last frame (indexes into the sequence; its frames
        are those between with its counter, repeats aside), whether it has every frame, and
        per sample whether a repeated frame flags it.

        Runs of one counter value are the unit: a run of distinct frames is one sample (complete
        when it has them all); a run with a repeat or more frames than a sample is split frame by
        frame (the module's rules)."""
        m = len(fid)
        nf = len(self.frame_ids)
        if m == 0:
            e = np.empty(0, np.int64)
            return e, e, np.empty(0, bool), np.empty(0, bool)
        start = np.flatnonzero(np.concatenate([[True], counter[1:] != counter[:-1]]))
        end = np.append(start[1:], m)
        length = end - start
        run = np.repeat(np.arange(len(start)), length)
        # a repeat in a run: equal (run, id) neighbours once sorted
        order = np.lexsort((fid, run))
        rep = (run[order][1:] == run[order][:-1]) & (fid[order][1:] == fid[order][:-1])
        irregular = np.zeros(len(start), bool)
        irregular[run[order][1:][rep]] = True
        irregular |= length > nf
        if not irregular.any():
            return start, end - 1, length == nf, np.zeros(len(start), bool)
        first: list[int] = []
        last: list[int] = []
        complete: list[bool] = []
        dup: list[bool] = []
        regular = ~irregular
        for r in range(len(start)):
            a, b = int(start[r]), int(end[r])
            if regular[r]:
                first.append(a)
                last.append(b - 1)
                complete.append(b - a == nf)
                dup.append(False)
                continue
            seen: set[int] = set()
            s0, marked = a, False
            for i in range(a, b):
                f = int(fid[i])
                if not seen:
                    s0, marked = i, False
                if f in seen:  # the same frame twice for one counter value: the first kept
                    self.bad += 1
                    marked = True
                    continue
                seen.add(f)
                if len(seen) == nf:
                    first.append(s0)
                    last.append(i)
                    complete.append(True)
                    dup.append(marked)
                    seen = set()
            if seen:
                first.append(s0)
                last.append(b - 1)
                complete.append(False)
                dup.append(marked)
        return (
            np.array(first, np.int64),
            np.array(last, np.int64),
            np.array(complete, bool),
            np.array(dup, bool),
        )

    @staticmethod
    def _marks(
        first_pos: np.ndarray, close_pos: np.ndarray, bad_pos: np.ndarray, dup: np.ndarray
    ) -> np.ndarray:
        """Per sample (and one more: after the last), whether a bad frame flags it: the sample
        open at the bad frame's position (after its first frame, before it closes), else the next
        one."""
        s = len(first_pos)
        marks = np.zeros(s + 1, bool)
        marks[:s] = dup
        if len(bad_pos) and not s:
            marks[0] = True
        elif len(bad_pos):
            j = np.searchsorted(first_pos, bad_pos) - 1
            inside = (j >= 0) & (close_pos[np.maximum(j, 0)] > bad_pos)
            marks[np.where(inside, j, j + 1)] = True
        return marks

    def _samples(
        self,
        counter: np.ndarray,
        fid: np.ndarray,
        groups: list[tuple[np.ndarray, dict[str, np.ndarray]]],
        starts: np.ndarray,
        k: int,
        complete: np.ndarray,
        marks: np.ndarray,
        t_all: np.ndarray,
        tb_all: np.ndarray,
        done_at: np.ndarray,
        bad: np.ndarray,
    ) -> Samples:
        """The first ``k`` samples of the sequence as columns (sample i: the frames from
        ``starts[i]`` to the next start, the first of each id), with the counter bookkeeping."""
        first = starts[:k]
        n_ch = self.n
        counts = np.full((k, n_ch), RAW_MISSING_COUNTS, np.int64)
        have = np.zeros((k, n_ch), bool)
        ch_status = np.zeros((k, n_ch), np.int64)
        if k:
            # each frame's sample; the first of equal (sample, id) pairs is the one used
            owner = np.searchsorted(starts, np.arange(len(fid)), side="right") - 1
            used = owner < k
            if bool(marks.any()):  # a repeated frame marks its sample: keep the first of each id
                idx = np.flatnonzero(used)
                order = idx[np.lexsort((idx, fid[idx], owner[idx]))]
                first_of = np.ones(len(order), bool)
                first_of[1:] = (owner[order][1:] != owner[order][:-1]) | (
                    fid[order][1:] != fid[order][:-1]
                )
                used = np.zeros(len(fid), bool)
                used[order[first_of]] = True
            for (sel, values), entries in zip(groups, self._entries, strict=True):
                if not len(sel):
                    continue
                u = used[sel]
                rows = owner[sel[u]]
                for ch, bit, sname in entries:
                    v = values[sname][u]
                    if not bit:
                        counts[rows, ch] = v
                        have[rows, ch] = True
                    else:
                        ch_status[rows, ch] |= np.where(v != 0, bit, 0)
        c = counter[first]
        ts = t_all[first]
        tb = tb_all[first]
        seq = self._bookkeeping(c, ts)
        T = self.calibration.to_newtons(np.where(have, counts, np.nan))
        status = np.zeros(k, np.int64)
        status[~complete] |= STATUS_GAP
        self.partial += int(np.count_nonzero(~complete))
        status[marks] |= STATUS_BAD_FRAME
        any_status = np.bitwise_or.reduce(ch_status, axis=1) if k else np.zeros(0, np.int64)
        status |= status_from_channel_bits(any_status)
        cols: dict[str, np.ndarray] = {}
        for j, key in enumerate(self._keys_T):
            cols[key] = np.ascontiguousarray(T[:, j], np.float64)
        for j, key in enumerate(self._keys_raw):
            cols[key] = counts[:, j].copy()
        for j, key in enumerate(self._keys_status):
            cols[key] = ch_status[:, j].copy()
        cols["counter"] = c.astype(np.int64)
        cols["seq"] = seq
        cols["t_bus_ns"] = tb.astype(np.int64)
        return Samples(ts.astype(np.int64), cols, status, done_at.astype(np.int64), bad)

    def _bookkeeping(self, c: np.ndarray, ts: np.ndarray) -> np.ndarray:
        """``seq`` of samples with counters ``c`` at times ``ts``; lost samples and pauses
        counted."""
        k = len(c)
        if not k:
            return np.empty(0, np.int64)
        prev_c = np.concatenate([[self._last_counter if self._last_counter is not None else -1],
                                 c[:-1]])  # fmt: skip
        prev_t = np.concatenate([[self._last_t_ns], ts[:-1]])
        step = (c - prev_c) % 256
        step[step == 0] = 256
        if self.rate_hz > 0:
            dt = ts - prev_t
            if self._last_counter is None:
                dt[0] = 0
            for i in np.flatnonzero(dt > self.wrap_ns):
                self.n_pauses += 1
                if len(self.pauses) < MAX_PAUSES:
                    self.pauses.append((int(prev_t[i]), int(dt[i])))
        if self._last_counter is None:
            step[0] = 0
            seq = c[0] + np.concatenate([[0], np.cumsum(step[1:])])
            self.lost += int(np.sum(step[1:] - 1))
        else:
            seq = self._seq + np.cumsum(step)
            self.lost += int(np.sum(step - 1))
        self._last_counter = int(c[-1])
        self._last_t_ns = int(ts[-1])
        self._seq = int(seq[-1])
        return seq.astype(np.int64)


def build_decoder(
    origin: str,
    prefix: str,
    dbc: str | Path | None,
    cables: Sequence[str] | None,
    offset_counts: Any,
    gain_N_per_count: Any,
    rate_hz: float = 0.0,
) -> tuple[LoadCellDecoder, str]:
    """A :class:`LoadCellDecoder` from driver settings; errors name ``origin`` and ``prefix.key``
    (a cable without its counts in the DBC: ``prefix.dbc``, the DBC's path in the problem)."""
    dbc_path = Path(dbc) if dbc is not None else DEFAULT_DBC
    db = load_dbc(dbc_path, origin, f"{prefix}.dbc")
    if cables is None:
        cables = default_cable_names(n_counts_channels(db))
    cables = [str(c) for c in cables]
    if len(set(cables)) != len(cables) or not cables:
        raise ConfigError(origin, f"{prefix}.cables", f"expected unique cable names, got {cables}")
    cal = calibration_from_settings(origin, prefix, len(cables), offset_counts, gain_N_per_count)
    try:
        dec = LoadCellDecoder(db, cables, cal, rate_hz)
    except ValueError as exc:  # a cable without its counts in the DBC: name the DBC
        raise ConfigError(origin, f"{prefix}.dbc", f"{dbc_path}: {exc}") from None
    return dec, str(dbc_path)
