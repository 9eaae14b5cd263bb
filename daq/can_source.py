"""CAN load cells: a python-can bus, frames decoded by cantools from a DBC, counts -> newtons.

The DBC (default ``data_samples/loadcell.dbc``) describes an 8-channel amplifier: signals named
``Ch<k>_Counts`` (raw counts), ``Ch<k>_Saturated`` / ``Ch<k>_Slack`` / ``Ch<k>_Fault`` (status bits)
and one ``Counter`` per frame (rolling sample counter shared by the frames of one sample).  Any DBC
following that naming works; the frames of one sample are the messages that carry a used channel.

Streams:

- ``can_raw``: every frame as it was on the bus, every field python-can gives it (layout and codec:
  :mod:`cdpr.daq.can_raw`, registered here).
- ``tensions``: one reading per sample: ``T_<cable>_N``, ``raw_<cable>_counts``, ``status_<cable>``
  (DBC bits: 1 saturated, 2 slack, 4 fault), ``counter`` (0..255), ``seq`` (unwrapped counter) and
  ``t_bus_ns`` of the first frame.  A sample with a missing frame comes out with NaN for the missing
  channels and :data:`STATUS_GAP`.

Counter gaps count as lost samples (``stats.lost``): the gap is what the 8-bit counter says,
modulo 256 (a jump from 10 to 13 is 2 lost, from 250 to 3 is 8 lost, the same value again 255).
Whole wraps cannot be seen in the counter, and are never guessed from host time: a host-time gap
between two samples longer than one wrap (256 samples, 1.28 s at 200 Hz) is a **pause** (a sender
or reader that stopped, or an outage of unknown size), counted in ``stats.extra["pauses"]`` with
its duration in ``stats.extra["pause_s"]`` (the recorder makes each one a ``pauses`` fault event).
Error frames are counted (``stats.errors``,
``stats.extra["error_frames"]``) and logged; a bus that raises on receive, reports bus-off
(``bus.state == BusState.ERROR``) or floods error frames is shut down and reopened with exponential
backoff (``stats.reopened``).
"""

from __future__ import annotations

import bisect
import logging
import math
import re
import time
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import can
import cantools

from cdpr.analysis.conventions import (
    CHANNEL_STATUS_FAULT,
    CHANNEL_STATUS_SATURATED,
    CHANNEL_STATUS_SLACK,
    status_from_channel_bits,
)
from cdpr.analysis.errors import ConfigError

from . import can_raw
from .loadcell import (
    RAW_MISSING_COUNTS,
    Calibration,
    calibration_from_settings,
    check_frame_budget,
)
from .mcap_writer import register_stream_codec
from .source import (
    STATUS_GAP,
    FieldDescription,
    Reading,
    ReopenBackoff,
    Source,
    StreamDescription,
)

log = logging.getLogger(__name__)

DEFAULT_DBC = Path(__file__).resolve().parent / "loadcell.dbc"
"""The DBC shipped inside the package (``daq/loadcell.dbc``, package data of ``cdpr.daq``;
``data_samples/loadcell.dbc`` links to it), so it is found in a wheel install too."""

_CH_RE = re.compile(r"^Ch(\d+)_(Counts|Saturated|Slack|Fault)$")
#: pauses kept in :attr:`LoadCellDecoder.pauses` (the count goes on)
MAX_PAUSES = 1000


def load_dbc(path: str | Path, origin: str = "<config>", key: str = "dbc") -> Any:
    """Load a DBC with cantools; a missing or invalid file raises :class:`ConfigError`."""
    p = Path(path)
    try:
        return cantools.database.load_file(str(p), database_format="dbc", strict=True)
    except FileNotFoundError:
        raise ConfigError(origin, key, f"DBC file not found: {p}") from None
    except Exception as exc:  # cantools raises several parser error types
        raise ConfigError(origin, key, f"cannot parse DBC {p}: {exc}") from None


def default_cable_names(n: int) -> list[str]:
    return [f"c{i + 1}" for i in range(n)]


class LoadCellDecoder:
    """Decodes load-cell frames (DBC naming above) into ``tensions`` readings.

    db: a cantools database; cables: one name per channel, channel k (1-based) -> ``cables[k-1]``;
    calibration: per-channel offsets and gains (len(cables) channels).
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
        self.channel_signals: dict[int, list[tuple[int, str, str]]] = {}
        for msg in db.messages:
            entries = []
            for sig in msg.signals:
                m = _CH_RE.match(sig.name)
                if m and 1 <= int(m.group(1)) <= n:
                    entries.append((int(m.group(1)) - 1, m.group(2), sig.name))
            if entries:
                self.channel_signals[msg.frame_id] = entries
        found = sorted({e[0] for v in self.channel_signals.values() for e in v})
        if found != list(range(n)):
            missing = sorted(set(range(n)) - set(found))
            raise ValueError(f"DBC has no Ch<k>_Counts for channels {[k + 1 for k in missing]}")
        self.frame_ids = sorted(self.channel_signals)
        bits = {
            "Counts": 0,
            "Saturated": CHANNEL_STATUS_SATURATED,
            "Slack": CHANNEL_STATUS_SLACK,
            "Fault": CHANNEL_STATUS_FAULT,
        }
        # per frame id: (channel, status bit or 0 for the counts, signal name)
        self._entries = {
            fid: [(ch, bits[what], sname) for ch, what, sname in v]
            for fid, v in self.channel_signals.items()
        }
        self._keys_T = [f"T_{c}_N" for c in self.cables]
        self._keys_raw = [f"raw_{c}_counts" for c in self.cables]
        self._keys_status = [f"status_{c}" for c in self.cables]
        self._cal: Calibration | None = None
        self._off_gain: list[tuple[float, float]] = []
        self._msgs = {fid: db.get_message_by_frame_id(fid) for fid in self.frame_ids}
        # fast path: Intel-order integer signals unpacked from one little-endian int, verified
        # against cantools on the first frame of every id (any mismatch -> cantools for good)
        self._fast: dict[int, list[tuple[str, int, int, bool]]] = {}
        self._checked: set[int] = set()
        for fid, m in self._msgs.items():
            if all(sg.byte_order == "little_endian" and not sg.is_float for sg in m.signals):
                self._fast[fid] = [
                    (sg.name, sg.start, (1 << sg.length) - 1, sg.is_signed) for sg in m.signals
                ]
        self.lost = 0
        self.partial = 0
        #: host-time gaps between two samples longer than a counter wrap: ``(t_ns, duration_ns)``
        #: of the last sample before each (at most MAX_PAUSES kept; ``n_pauses`` counts them all)
        self.pauses: list[tuple[int, int]] = []
        self.n_pauses = 0
        #: one wrap of the 8-bit counter (ns); 0: unknown rate, no pause detection
        self.wrap_ns = int(round(256e9 / self.rate_hz)) if self.rate_hz > 0 else 0
        self.bad = 0
        self._last_counter: int | None = None
        self._last_t_ns = 0
        self._seq = -1
        self._pending_counter: int | None = None
        self._pending: dict[int, dict[str, Any]] = {}
        self._pending_t: tuple[int, int] = (0, 0)

    @property
    def frames_per_sample(self) -> int:
        return len(self.frame_ids)

    def reset(self) -> None:
        """Drop the pending sample (after a bus reopen).  The counter history stays: the device kept
        counting, so the gap over the outage is counted as lost samples."""
        self._pending_counter = None
        self._pending = {}

    def decode(self, msg: can.Message, t_ns: int) -> list[Reading]:
        """Feed one frame; returns the completed (or flushed partial) samples, usually 0 or 1."""
        fid = msg.arbitration_id
        m = self._msgs.get(fid)
        # the id with its extended flag: an extended frame whose id equals a standard load-cell
        # id is another frame
        if (
            m is None
            or bool(m.is_extended_frame) != bool(msg.is_extended_id)
            or msg.is_error_frame
            or msg.is_remote_frame
        ):
            return []
        data = bytes(msg.data)
        try:
            fast = self._fast.get(fid)
            if fast is not None and len(data) == self._msgs[fid].length:
                sig = self._unpack(fast, data)
                if fid not in self._checked:
                    ref = self._msgs[fid].decode(data, decode_choices=False, scaling=False)
                    if ref != sig:
                        log.warning(
                            "fast unpack of 0x%X disagrees with cantools: using cantools", fid
                        )
                        del self._fast[fid]
                        sig = ref
                    self._checked.add(fid)
            else:
                sig = self._msgs[fid].decode(data, decode_choices=False, scaling=False)
        except Exception:
            self.bad += 1
            return []
        counter = int(sig.get("Counter", 0))
        out: list[Reading] = []
        if self._pending_counter is not None and counter != self._pending_counter:
            out.append(self._flush())
        if self._pending_counter is None:
            self._pending_counter = counter
            self._pending_t = (t_ns, int(round(msg.timestamp * 1e9)))
        if fid in self._pending:
            # the same frame twice for one counter value: keep the first, count it as bad
            self.bad += 1
            return out
        self._pending[fid] = sig
        if len(self._pending) == len(self.frame_ids):
            out.append(self._flush())
        return out

    @staticmethod
    def _unpack(fast: list[tuple[str, int, int, bool]], data: bytes) -> dict[str, int]:
        word = int.from_bytes(data, "little")
        out = {}
        for name, start, mask, signed in fast:
            v = (word >> start) & mask
            if signed and v > mask >> 1:
                v -= mask + 1
            out[name] = v
        return out

    def _pause(self, t_ns: int, duration_ns: int) -> None:
        self.n_pauses += 1
        if len(self.pauses) < MAX_PAUSES:
            self.pauses.append((t_ns, duration_ns))

    def decode_block(
        self,
        ids: Any,
        extended: Any,
        data: Any,
        lengths: Any,
        t_ns: Any,
        t_bus_ns: Any,
    ) -> tuple[int, dict[str, Any] | None]:
        """Decode the regular start of a block of load-cell frames at once (the import's hot path).

        Arguments are columns of the load-cell frames only (no error or remote frames): ids, the
        extended flags, data (n, >= 8) uint8 with ``lengths``, log and bus times (int64 ns).  The
        regular start is the longest run of whole samples, each the DBC's frames once with one
        counter, taken when no sample is pending and every frame is of the fast-unpack kind; its
        samples are what :meth:`decode` would give frame by frame (same values, counter
        bookkeeping and lost count).  Returns how many frames were used and the samples as columns
        (``t_ns``, ``status``, then the ``tensions`` fields in order), or ``(0, None)``: the caller
        feeds the rest to :meth:`decode`."""
        import numpy as np

        nf = len(self.frame_ids)
        n = len(ids)
        cal = self.calibration
        if (
            self._pending_counter is not None
            or n < nf
            or type(cal) is not Calibration
            or any(f not in self._fast for f in self.frame_ids)
        ):
            return 0, None
        ids = np.asarray(ids, np.int64)
        fids = np.asarray(self.frame_ids, np.int64)
        lens_ok = np.asarray([self._msgs[f].length for f in self.frame_ids], np.int64)[
            np.searchsorted(fids, np.clip(ids, fids[0], fids[-1]))
        ]
        regular = (
            np.isin(ids, fids) & ~np.asarray(extended, bool) & (np.asarray(lengths) == lens_ok)
        )
        m = (n // nf) * nf
        bad = np.flatnonzero(~regular[:m])
        if bad.size:
            m = (int(bad[0]) // nf) * nf
        if m == 0:
            return 0, None
        d8 = np.zeros((m, 8), np.uint8)
        d8[:, : min(8, data.shape[1])] = data[:m, :8]
        word = d8.view("<u8").ravel()
        ids_m = ids[:m]
        # every first frame of an id is checked against cantools once (as decode does)
        for fid in self.frame_ids:
            if fid not in self._checked:
                i = int(np.flatnonzero(ids_m == fid)[0])
                raw = bytes(d8[i, : int(lengths[i])])
                if self._msgs[fid].decode(raw, decode_choices=False, scaling=False) != (
                    self._unpack(self._fast[fid], raw)
                ):
                    return 0, None
                self._checked.add(fid)
        grp = ids_m.reshape(-1, nf)
        if not np.array_equal(np.sort(grp, axis=1), np.broadcast_to(fids, grp.shape)):
            # the frames of a sample are not each id once: find the first such sample
            ok = (np.sort(grp, axis=1) == fids).all(axis=1)
            m = int(np.argmin(ok)) * nf if not ok.all() else m
            if m == 0:
                return 0, None
            grp, word, ids_m = grp[: m // nf], word[:m], ids_m[:m]
        k = m // nf
        n_ch = self.n
        counts = np.zeros((k, n_ch), np.int64)
        ch_status = np.zeros((k, n_ch), np.int64)
        counter = np.full(m, -1, np.int64)
        for fid in self.frame_ids:
            sel = ids_m == fid
            w = word[sel]
            sig: dict[str, Any] = {}
            for name, start, mask, signed in self._fast[fid]:
                v = ((w >> np.uint64(start)) & np.uint64(mask)).astype(np.int64)
                if signed:
                    v = np.where(v > mask >> 1, v - (mask + 1), v)
                sig[name] = v
            counter[sel] = sig.get("Counter", np.zeros(int(sel.sum()), np.int64))
            rows = np.flatnonzero(sel) // nf
            for ch, bit, sname in self._entries[fid]:
                if not bit:
                    counts[rows, ch] = sig[sname]
                else:
                    ch_status[rows, ch] |= np.where(sig[sname] != 0, bit, 0)
        cgrp = counter.reshape(k, nf)
        same = (cgrp == cgrp[:, :1]).all(axis=1)
        if not same.all():
            k = int(np.argmin(same))
            if k == 0:
                return 0, None
            m = k * nf
            counts, ch_status, cgrp = counts[:k], ch_status[:k], cgrp[:k]
        c = cgrp[:, 0]
        first = np.arange(k) * nf
        ts = np.asarray(t_ns, np.int64)[:m][first]
        tb = np.asarray(t_bus_ns, np.int64)[:m][first]
        # counter bookkeeping, as _flush does one sample at a time
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
                self._pause(int(prev_t[i]), int(dt[i]))
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
        T = cal.to_newtons(counts)
        any_status = np.bitwise_or.reduce(ch_status, axis=1)
        status = status_from_channel_bits(any_status)
        cols: dict[str, Any] = {"t_ns": ts, "status": status}
        for j, key in enumerate(self._keys_T):
            cols[key] = T[:, j]
        for j, key in enumerate(self._keys_raw):
            cols[key] = counts[:, j]
        for j, key in enumerate(self._keys_status):
            cols[key] = ch_status[:, j]
        cols["counter"] = c
        cols["seq"] = seq
        cols["t_bus_ns"] = tb
        return m, cols

    def flush(self) -> list[Reading]:
        """Emit a pending incomplete sample (at close)."""
        return [self._flush()] if self._pending_counter is not None else []

    def _flush(self) -> Reading:
        counter = self._pending_counter
        assert counter is not None
        t_ns, t_bus_ns = self._pending_t
        if self._last_counter is None:
            self._seq = counter
        else:
            step = (counter - self._last_counter) % 256
            if step == 0:
                step = 256
            if self.rate_hz > 0 and t_ns - self._last_t_ns > self.wrap_ns:
                self._pause(self._last_t_ns, t_ns - self._last_t_ns)
            self.lost += step - 1
            self._seq += step
        self._last_counter = counter
        self._last_t_ns = t_ns
        n = self.n
        counts: list[Any] = [math.nan] * n
        ch_status = [0] * n
        entries = self._entries
        for fid, sig in self._pending.items():
            for ch, bit, sname in entries[fid]:
                v = sig[sname]
                if not bit:
                    counts[ch] = v
                elif v:
                    ch_status[ch] |= bit
        status = 0
        if len(self._pending) < len(self.frame_ids):
            status |= STATUS_GAP
            self.partial += 1
        cal = self.calibration
        if type(cal) is Calibration:
            # T = (counts - offset) * gain in plain floats: the same IEEE operations as
            # Calibration.to_newtons, without a numpy round trip per sample
            if cal is not self._cal:
                self._cal = cal
                self._off_gain = list(
                    zip(cal.offset_counts.tolist(), cal.gain_N_per_count.tolist(), strict=True)
                )
            tensions = [
                (float(c) - o) * g for c, (o, g) in zip(counts, self._off_gain, strict=True)
            ]
        else:
            tensions = [float(t) for t in cal.to_newtons(counts)]
        values: dict[str, Any] = dict(zip(self._keys_T, tensions, strict=True))
        for key, c in zip(self._keys_raw, counts, strict=True):
            values[key] = int(c) if c == c else RAW_MISSING_COUNTS
        any_status = 0
        for key, st in zip(self._keys_status, ch_status, strict=True):
            values[key] = st
            any_status |= st
        if any_status:
            status |= status_from_channel_bits(int(any_status))
        values["counter"] = counter
        values["seq"] = self._seq
        values["t_bus_ns"] = t_bus_ns
        self._pending_counter = None
        self._pending = {}
        return Reading("tensions", t_ns, values, status)

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


CAN_RAW_DESCRIPTION = can_raw.DESCRIPTION
raw_reading = can_raw.raw_reading


class CanFrameBatch(Sequence[Reading]):
    """The readings of one :meth:`CanLoadCellSource.read`: raw frames kept as ``can.Message`` plus
    host reception times (``t_ns``), and the other readings (decoded ``tensions``) in between.

    It is a sequence of :class:`Reading` like any source's batch: indexing or iterating turns a
    frame into its ``can_raw`` reading (:func:`raw_reading`) only when it is looked at.  The
    recorder's writer does not look: it formats the frames of a batch directly into MCAP records
    (:meth:`cdpr.daq.mcap_writer.McapRunWriter.write_many`), which saves building a ``Reading`` and a
    dict per frame on a busy bus.

    stream: stream name of the frames (``can_raw``, or ``<source>/can_raw`` once renamed).
    messages, t_ns: the frames and their host reception times (integer ns since the Unix epoch).
    others: ``(k, reading)``: ``reading`` came after the first ``k`` frames.
    """

    __slots__ = ("stream", "messages", "t_ns", "others", "_pos")

    def __init__(
        self,
        stream: str = "can_raw",
        messages: list[can.Message] | None = None,
        t_ns: list[int] | None = None,
        others: list[tuple[int, Reading]] | None = None,
    ) -> None:
        self.stream = stream
        self.messages: list[can.Message] = [] if messages is None else messages
        self.t_ns: list[int] = [] if t_ns is None else t_ns
        self.others: list[tuple[int, Reading]] = [] if others is None else others
        self._pos: list[int] | None = None

    def add_frame(self, msg: can.Message, t_ns: int) -> None:
        self.messages.append(msg)
        self.t_ns.append(t_ns)

    def add_reading(self, reading: Reading) -> None:
        self.others.append((len(self.messages), reading))
        self._pos = None

    def frame_reading(self, i: int) -> Reading:
        """The ``can_raw`` reading of frame ``i``."""
        return raw_reading(self.messages[i], self.t_ns[i], self.stream)

    def renamed(self, renames: Mapping[str, str]) -> CanFrameBatch:
        """The same batch with streams renamed (``{"can_raw": "bus_a/can_raw", ...}``)."""
        others = [
            (
                k,
                Reading(renames[r.stream], r.t_ns, r.values, r.status)
                if r.stream in renames
                else r,
            )
            for k, r in self.others
        ]
        return CanFrameBatch(
            renames.get(self.stream, self.stream), self.messages, self.t_ns, others
        )

    @classmethod
    def join(cls, batches: Sequence[CanFrameBatch]) -> CanFrameBatch:
        """One batch of consecutive batches of the same stream (in order)."""
        out = cls(batches[0].stream)
        for b in batches:
            k = len(out.messages)
            out.others.extend((k + i, r) for i, r in b.others)
            out.messages.extend(b.messages)
            out.t_ns.extend(b.t_ns)
        return out

    def latest(self) -> dict[str, Reading]:
        """The last reading of every stream in the batch."""
        out: dict[str, Reading] = {}
        if self.messages:
            out[self.stream] = self.frame_reading(len(self.messages) - 1)
        for _, r in self.others:
            out[r.stream] = r
        return out

    def __len__(self) -> int:
        return len(self.messages) + len(self.others)

    def _positions(self) -> list[int]:
        # position of every other reading in the combined order
        if self._pos is None:
            self._pos = [k + j for j, (k, _) in enumerate(self.others)]
        return self._pos

    def _one(self, i: int) -> Reading:
        n = len(self)
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError("batch index out of range")
        if not self.others:
            return self.frame_reading(i)
        pos = self._positions()
        j = bisect.bisect_left(pos, i)
        if j < len(pos) and pos[j] == i:
            return self.others[j][1]
        return self.frame_reading(i - j)

    def __getitem__(self, i: Any) -> Any:
        if isinstance(i, slice):
            return [self._one(k) for k in range(*i.indices(len(self)))]
        return self._one(i)

    def __iter__(self) -> Iterator[Reading]:
        others = self.others
        j = 0
        for i in range(len(self.messages)):
            while j < len(others) and others[j][0] <= i:
                yield others[j][1]
                j += 1
            yield self.frame_reading(i)
        for _, r in others[j:]:
            yield r

    def __repr__(self) -> str:
        return (
            f"CanFrameBatch({self.stream!r}, {len(self.messages)} frames, "
            f"{len(self.others)} other readings)"
        )


def build_decoder(
    origin: str,
    prefix: str,
    dbc: str | Path | None,
    cables: Sequence[str] | None,
    offset_counts: Any,
    gain_N_per_count: Any,
    rate_hz: float = 0.0,
) -> tuple[LoadCellDecoder, str]:
    """A :class:`LoadCellDecoder` from driver settings; errors name ``origin`` and ``prefix.key``."""
    dbc_path = Path(dbc) if dbc is not None else DEFAULT_DBC
    db = load_dbc(dbc_path, origin, f"{prefix}.dbc")
    if cables is None:
        n_dbc = len(
            {
                int(m.group(1))
                for msg in db.messages
                for s in msg.signals
                if (m := _CH_RE.match(s.name)) and m.group(2) == "Counts"
            }
        )
        cables = default_cable_names(n_dbc)
    cables = [str(c) for c in cables]
    if len(set(cables)) != len(cables) or not cables:
        raise ConfigError(origin, f"{prefix}.cables", f"expected unique cable names, got {cables}")
    cal = calibration_from_settings(origin, prefix, len(cables), offset_counts, gain_N_per_count)
    try:
        dec = LoadCellDecoder(db, cables, cal, rate_hz)
    except ValueError as exc:
        raise ConfigError(origin, f"{prefix}.cables", f"{exc} ({dbc_path})") from None
    return dec, str(dbc_path)


GATHER_S = 0.005
#: error class bit of a SocketCAN error frame's id (linux/can/error.h): the controller is bus-off
CAN_ERR_BUSOFF = 0x40
"""After the first frame of a read, :meth:`CanLoadCellSource.read` keeps receiving for this long (s)."""


class CanLoadCellSource(Source):
    """Load cells on a CAN bus (python-can), decoded with a DBC.

    Settings (keyword arguments; ``interface``, ``channel`` and ``bitrate`` are required and always
    passed to python-can, so ``~/can.conf`` and ``CAN_*`` variables never change the bus):

    interface: python-can interface (``"virtual"``, ``"slcan"``, ``"socketcan"``, ``"pcan"``, ...).
    channel: channel (virtual bus name, serial port of an slcan adapter, ``can0``, ...).
    bitrate: bus bit rate, bit/s.
    rate_hz: nominal sample rate of the amplifier (for the frame budget and ``describe``), Hz.
    dbc: DBC path (default: ``data_samples/loadcell.dbc``).
    cables: cable names in channel order (default ``c1..c8``).
    offset_counts, gain_N_per_count: calibration, one value or one per channel.
    max_bus_load: the largest allowed worst-case bus load fraction (default 0.9).
    bus_options: extra keyword arguments for ``can.Bus`` (e.g. ``sleep_after_open`` for slcan).
    raw: emit the ``can_raw`` stream (default True); decode: emit ``tensions`` (default True).
    reopen_backoff_s: (first, max) delay between reopen attempts, s.
    """

    kind = "can_loadcell"
    accepts_origin = True

    def __init__(
        self,
        name: str,
        interface: str,
        channel: str,
        bitrate: int,
        rate_hz: float = 200.0,
        dbc: str | None = None,
        cables: Sequence[str] | None = None,
        offset_counts: Any = None,
        gain_N_per_count: Any = None,
        max_bus_load: float = 0.9,
        bus_options: dict[str, Any] | None = None,
        raw: bool = True,
        decode: bool = True,
        reopen_backoff_s: Sequence[float] = (0.1, 5.0),
        error_frame_limit: int = 1000,
        origin: str = "<config>",
    ) -> None:
        super().__init__(name)
        prefix = f"sources.{name}"
        self.origin = origin
        # types and ranges: checked by create_source (cdpr.daq.source_schema.CanLoadCellSettings)
        bitrate, rate_hz = int(bitrate), float(rate_hz)
        self.interface = interface
        self.channel = str(channel)
        self.bitrate = bitrate
        self.rate_hz = rate_hz
        self.decoder, self.dbc_path = build_decoder(
            origin, prefix, dbc, cables, offset_counts, gain_N_per_count, rate_hz
        )
        self.budget = check_frame_budget(
            origin,
            prefix,
            bitrate,
            rate_hz,
            self.decoder.frames_per_sample,
            max(m.length for m in self.decoder._msgs.values()),
            any(m.is_extended_frame for m in self.decoder._msgs.values()),
            max_bus_load,
        )
        self.max_bus_load = float(max_bus_load)
        self.bus_options = dict(bus_options or {})
        self.emit_raw = bool(raw)
        self.emit_decoded = bool(decode)
        self.backoff = (float(reopen_backoff_s[0]), float(reopen_backoff_s[1]))
        self.error_frame_limit = int(error_frame_limit)
        self.bus: can.BusABC | None = None
        self._reopen = ReopenBackoff(*self.backoff)
        self._err_window = (0.0, 0)
        self._last_state_check = 0.0
        self._ever_opened = False

    # settings / describe ------------------------------------------------------------------
    def settings(self) -> dict[str, Any]:
        return {
            "interface": self.interface,
            "channel": self.channel,
            "bitrate": self.bitrate,
            "rate_hz": self.rate_hz,
            "dbc": self.dbc_path,
            "cables": list(self.decoder.cables),
            **self.decoder.calibration.to_mapping(),
            "max_bus_load": self.max_bus_load,
            "bus_options": dict(self.bus_options),
            "frame_budget_load": round(self.budget.load, 4),
        }

    def describe(self) -> dict[str, StreamDescription]:
        out: dict[str, StreamDescription] = {}
        if self.emit_raw:
            d = CAN_RAW_DESCRIPTION
            out["can_raw"] = StreamDescription(d.fields, self.budget.frames_per_s, d.doc)
        if self.emit_decoded:
            out["tensions"] = self.decoder.describe(self.rate_hz)
        return out

    # lifecycle ----------------------------------------------------------------------------
    def _make_bus(self) -> can.BusABC:
        return can.Bus(
            interface=self.interface,
            channel=self.channel,
            bitrate=self.bitrate,
            **self.bus_options,
        )

    def _open(self) -> None:
        try:
            self.bus = self._make_bus()
        except (can.CanError, OSError, ValueError) as exc:
            raise ConfigError(
                self.origin,
                f"sources.{self.name}.channel",
                f"cannot open {self.interface} bus {self.channel!r}: {exc}",
            ) from None
        self._ever_opened = True

    def _close(self) -> None:
        self._drop_bus()

    def _drop_bus(self) -> None:
        bus, self.bus = self.bus, None
        if bus is not None:
            try:
                bus.shutdown()
            except Exception as exc:  # a dead device can fail to shut down; nothing to save
                log.debug("%s: shutdown failed: %s", self.name, exc)

    def _fail(self, why: str) -> None:
        self.stats.errors += 1
        log.warning("%s: %s; reopening the bus in %.2f s", self.name, why, self._reopen.delay_s)
        self._drop_bus()
        self.decoder.reset()
        self._reopen.failed()

    def _try_reopen(self, timeout_s: float) -> bool:
        if not self._reopen.due(timeout_s):
            return False
        try:
            self.bus = self._make_bus()
        except Exception as exc:
            log.info("%s: reopen failed: %s", self.name, exc)
            self._reopen.failed()
            return False
        self.stats.reopened += 1
        self._reopen.succeeded()
        log.warning("%s: bus reopened", self.name)
        return True

    # data ---------------------------------------------------------------------------------
    def _read(self, timeout_s: float) -> CanFrameBatch:  # type: ignore[override]
        if self.bus is None and not self._try_reopen(timeout_s):
            return CanFrameBatch()
        bus = self.bus
        assert bus is not None
        out = CanFrameBatch()
        # the hot path of a busy bus: a good frame is only kept (with its reception time) when it
        # needs no decoding; the batch turns frames into readings when someone looks at them
        add_frame = out.messages.append
        add_time = out.t_ns.append
        time_ns = time.time_ns
        recv = bus.recv
        fast = self.emit_raw and not self.emit_decoded
        handle = self._handle
        n = 0
        deadline = time.monotonic() + timeout_s
        gather_until = deadline
        wait = timeout_s
        monotonic = time.monotonic
        try:
            # bounded by time, not by a frame count: a backlog (a starved process) is handed to the
            # writer in slices of at most ~timeout_s, never held back for seconds
            while True:
                if n & 63 == 63 and monotonic() >= gather_until:
                    break
                msg = recv(timeout=wait)
                if msg is None:
                    now = time.monotonic()
                    if now >= gather_until:
                        break
                    wait = gather_until - now
                    continue
                if n == 0:
                    # after the first frame, gather what follows for a few ms: a busy bus then
                    # gives batches of hundreds of frames instead of one or two per read
                    gather_until = min(deadline, time.monotonic() + GATHER_S)
                wait = 0.0
                n += 1
                if fast and not msg.is_error_frame:
                    add_frame(msg)
                    add_time(time_ns())
                else:
                    handle(msg, out)
        except (can.CanError, OSError, ValueError) as exc:
            self._fail(f"receive failed ({type(exc).__name__}: {exc})")
            return out
        now = time.monotonic()
        if now - self._last_state_check > 1.0:
            self._last_state_check = now
            try:
                state = bus.state
            except Exception:
                state = None
            if state == can.BusState.ERROR:
                self.stats.extra["bus_off"] = self.stats.extra.get("bus_off", 0) + 1
                self._fail("bus-off")
        return out

    def _handle(self, msg: can.Message, out: CanFrameBatch) -> None:
        t_ns = time.time_ns()
        if msg.is_error_frame:
            self.stats.errors += 1
            self.stats.extra["error_frames"] = self.stats.extra.get("error_frames", 0) + 1
            t0, k = self._err_window
            now = time.monotonic()
            if now - t0 > 1.0:
                t0, k = now, 0
            k += 1
            self._err_window = (t0, k)
            if k == 1:
                log.warning(
                    "%s: CAN error frame (id 0x%X data %s)",
                    self.name,
                    msg.arbitration_id,
                    bytes(msg.data).hex(),
                )
            if msg.arbitration_id & CAN_ERR_BUSOFF:
                # SocketCAN reports bus-off as an error frame of class CAN_ERR_BUSOFF: the
                # controller has left the bus; reopening it restarts the controller
                self.stats.extra["bus_off"] = self.stats.extra.get("bus_off", 0) + 1
                if self.emit_raw:
                    out.add_frame(msg, t_ns)
                raise can.CanOperationError("bus-off (error frame class CAN_ERR_BUSOFF)")
            if k > self.error_frame_limit:
                self._err_window = (now, 0)
                if self.emit_raw:
                    out.add_frame(msg, t_ns)
                raise can.CanOperationError(f"more than {self.error_frame_limit} error frames/s")
        if self.emit_raw:
            out.add_frame(msg, t_ns)
        if self.emit_decoded:
            lost0, bad0 = self.decoder.lost, self.decoder.bad
            for r in self.decoder.decode(msg, t_ns):
                out.add_reading(r)
            self.stats.lost += self.decoder.lost - lost0
            self.stats.bad += self.decoder.bad - bad0
            self.stats.extra["partial_samples"] = self.decoder.partial
            if self.decoder.n_pauses != self.stats.extra.get("pauses", 0):
                self.stats.extra["pauses"] = self.decoder.n_pauses
                self.stats.extra["pause_s"] = tuple(
                    round(d * 1e-9, 3) for _, d in self.decoder.pauses
                )


can_raw.register(CanFrameBatch, register_stream_codec)
