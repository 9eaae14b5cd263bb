"""What a load-cell DBC says, and the signals of frames unpacked with it (:class:`LoadCellDbc`).

The DBC (default ``daq/loadcell.dbc``) describes an amplifier: signals named ``Ch<k>_Counts`` (raw
counts), ``Ch<k>_Saturated`` / ``Ch<k>_Slack`` / ``Ch<k>_Fault`` (status bits) and one ``Counter``
per frame (rolling sample counter shared by the frames of one sample).  Any DBC following that
naming works; the frames of one sample are the messages that carry a used channel; every cable
needs its ``Ch<k>_Counts``.  Intel-order integer signals of frames of at most 8 bytes (the usual
amplifier) are unpacked from one little-endian integer per frame with numpy, checked against
cantools on the first frame of every id (a mismatch: cantools for that id for good); any other
layout through cantools, frame by frame.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cantools
import numpy as np

from cdpr.analysis.conventions import (
    CHANNEL_STATUS_FAULT,
    CHANNEL_STATUS_SATURATED,
    CHANNEL_STATUS_SLACK,
)
from cdpr.analysis.errors import ConfigError

from .can_frames import ERROR, EXTENDED, REMOTE, FrameColumns

log = logging.getLogger(__name__)

DEFAULT_DBC = Path(__file__).resolve().parent / "loadcell.dbc"
"""The DBC shipped inside the package (``daq/loadcell.dbc``, package data of ``cdpr.daq``;
``data_samples/loadcell.dbc`` links to it), so it is found in a wheel install too."""

_CH_RE = re.compile(r"^Ch(\d+)_(Counts|Saturated|Slack|Fault)$")
_BITS = {
    "Counts": 0,
    "Saturated": CHANNEL_STATUS_SATURATED,
    "Slack": CHANNEL_STATUS_SLACK,
    "Fault": CHANNEL_STATUS_FAULT,
}


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


def n_counts_channels(db: Any) -> int:
    """How many channels a DBC gives counts for."""
    return len(
        {
            int(m.group(1))
            for msg in db.messages
            for s in msg.signals
            if (m := _CH_RE.match(s.name)) and m.group(2) == "Counts"
        }
    )


class LoadCellDbc:
    """The load-cell frames of a DBC for ``cables`` (channel k, 1-based -> ``cables[k-1]``):
    their ids, lengths, extended flags, the channel signals each carries (``entries[j]`` of
    ``frame_ids[j]``: channel index, status bit or 0 for the counts, signal name), and the signals
    of frames unpacked (:meth:`signals`).  A cable without its counts is a ValueError naming it."""

    def __init__(self, db: Any, cables: Sequence[str]) -> None:
        n = len(cables)
        #: frame id -> [(channel index, what, signal name)] of the channels it carries
        self.channel_signals: dict[int, list[tuple[int, str, str]]] = {}
        for msg in db.messages:
            entries = []
            for sig in msg.signals:
                m = _CH_RE.match(sig.name)
                if m and 1 <= int(m.group(1)) <= n:
                    entries.append((int(m.group(1)) - 1, m.group(2), sig.name))
            if entries:
                self.channel_signals[msg.frame_id] = entries
        # every cable needs its counts (status bits alone would make it 0 N, status 0)
        found = {e[0] for v in self.channel_signals.values() for e in v if e[1] == "Counts"}
        missing = [k for k in range(n) if k not in found]
        if missing:
            k = missing[0]
            raise ValueError(
                f"no Ch{k + 1}_Counts signal for cable {cables[k]!r} (channel {k + 1} of "
                f"{n})" + (f" nor for {len(missing) - 1} more" if len(missing) > 1 else "")
            )
        self.frame_ids = sorted(self.channel_signals)
        self._msgs = {fid: db.get_message_by_frame_id(fid) for fid in self.frame_ids}
        self._signal_names = sorted({sg.name for m in self._msgs.values() for sg in m.signals})
        self._fids = np.array(self.frame_ids, np.int64)
        self._flen = np.array([self._msgs[f].length for f in self.frame_ids], np.int64)
        self._fext = np.array([bool(self._msgs[f].is_extended_frame) for f in self.frame_ids])
        #: per frame id (index): (channel, status bit or 0 for the counts, signal name)
        self.entries = [
            [(ch, _BITS[what], sname) for ch, what, sname in self.channel_signals[fid]]
            for fid in self.frame_ids
        ]
        # the fast path: Intel-order integer signals of frames of at most 8 bytes, unpacked from
        # one little-endian uint64 with numpy; verified against cantools on the first frame of
        # every id (any mismatch: cantools for that id for good)
        self._fast: dict[int, list[tuple[str, int, int, bool]]] = {}
        self._checked: set[int] = set()
        for fid, m in self._msgs.items():
            if m.length <= 8 and all(
                sg.byte_order == "little_endian" and not sg.is_float for sg in m.signals
            ):
                self._fast[fid] = [
                    (sg.name, sg.start, (1 << sg.length) - 1, sg.is_signed) for sg in m.signals
                ]

    @property
    def max_frame_bytes(self) -> int:
        return int(self._flen.max())

    @property
    def extended_ids(self) -> bool:
        return bool(self._fext.any())

    def fid_index(self, ids: np.ndarray) -> np.ndarray:
        return np.searchsorted(self._fids, ids)

    def load_cell_frames(self, frames: FrameColumns) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Indexes of the load-cell frames, their frame-id index, and which of them have another
        length than the DBC's."""
        ids = frames.arbitration_id
        k = np.minimum(self.fid_index(ids), len(self._fids) - 1)
        fl = frames.flags
        is_lc = (
            (self._fids[k] == ids)
            & (((fl & EXTENDED) != 0) == self._fext[k])
            & ((fl & (ERROR | REMOTE)) == 0)
        )
        lc = np.flatnonzero(is_lc)
        k = k[lc]
        return lc, k, frames.length[lc] != self._flen[k]

    def signals(
        self, data: np.ndarray, length: np.ndarray, k: np.ndarray
    ) -> tuple[np.ndarray, list[tuple[np.ndarray, dict[str, np.ndarray]]], np.ndarray]:
        """The signals of load-cell frames of the DBC's lengths (``data`` (m, w), ``length``,
        ``k``: their frame-id index): the counters (m,), per frame id ``j`` the indexes of its
        frames and their raw signal values, and which frames cantools could not decode."""
        m = len(k)
        counter = np.zeros(m, np.int64)
        groups: list[tuple[np.ndarray, dict[str, np.ndarray]]] = []
        undecodable = np.zeros(m, bool)
        for j, fid in enumerate(self.frame_ids):
            sel = np.flatnonzero(k == j)
            if len(sel):
                values = self._unpack_fast(fid, data[sel], length[sel])
                if values is None:
                    values, failed = self._unpack_cantools(fid, data[sel], length[sel])
                    undecodable[sel[failed]] = True
                if "Counter" in values:
                    counter[sel] = values["Counter"]
            else:
                values = {}
            groups.append((sel, values))
        return counter, groups, undecodable

    def _unpack_fast(self, fid: int, data: np.ndarray, length: np.ndarray) -> Any:
        fast = self._fast.get(fid)
        if fast is None:
            return None
        d8 = np.zeros((len(data), 8), np.uint8)
        w = min(8, data.shape[1])
        d8[:, :w] = data[:, :w]
        word = d8.view("<u8").ravel()
        out = {}
        for name, start, mask, signed in fast:
            v = ((word >> np.uint64(start)) & np.uint64(mask)).astype(np.int64)
            if signed:
                v = np.where(v > mask >> 1, v - (mask + 1), v)
            out[name] = v
        if fid not in self._checked:  # the first frame of the id against cantools, once
            raw = bytes(data[0, : int(length[0])])
            ref = self._msgs[fid].decode(raw, decode_choices=False, scaling=False)
            self._checked.add(fid)
            if ref != {name: int(v[0]) for name, v in out.items()}:
                log.warning("fast unpack of 0x%X disagrees with cantools: using cantools", fid)
                del self._fast[fid]
                return None
        return out

    def _unpack_cantools(
        self, fid: int, data: np.ndarray, length: np.ndarray
    ) -> tuple[dict[str, np.ndarray], np.ndarray]:
        """cantools, frame by frame (a DBC with big-endian or float signals)."""
        msg = self._msgs[fid]
        names = [s.name for s in msg.signals]
        vals = np.zeros((len(names), len(data)), np.int64)
        failed = np.zeros(len(data), bool)
        for i in range(len(data)):
            try:
                d = msg.decode(bytes(data[i, : int(length[i])]), decode_choices=False,
                               scaling=False)  # fmt: skip
            except Exception:
                failed[i] = True
                continue
            for j, name in enumerate(names):
                vals[j, i] = int(d[name])
        return dict(zip(names, vals, strict=True)), failed
