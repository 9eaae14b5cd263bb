"""CAN frames as columns (:class:`FrameColumns`): what every log reader (:mod:`cdpr.daq.canlog`)
gives, what the load-cell decoder (:mod:`cdpr.daq.can_decoder`) reads and what ``/can_raw`` stores
(:mod:`cdpr.daq.can_raw`), whether the frames came from a log file or a live bus.

A frame has every field python-can gives a ``can.Message``; :meth:`FrameColumns.message` and
:meth:`FrameColumns.from_messages` convert both ways.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

#: flag bits of :attr:`FrameColumns.flags`; ODD: a frame a classic bus cannot carry as the log
#: gives it (an ASC line with a DLC past 15 or more than 8 bytes), read as python-can reads it
EXTENDED, ERROR, REMOTE, FD, BRS, ESI, RX, ODD = 1, 2, 4, 8, 16, 32, 64, 128

#: the largest timestamp (s) whose integer ns fits an int64 (the year 2262)
T_MAX_S = 9.2e9
T_PROBLEM = "timestamp out of range (its integer ns would pass the year 2262)"


@dataclass
class FrameColumns:
    """A block of CAN frames as columns.

    t_s: timestamps (float64 s, as python-can gives them); arbitration_id (int64); flags (uint8:
    :data:`EXTENDED`, :data:`ERROR`, :data:`REMOTE`, :data:`FD`, :data:`BRS`, :data:`ESI`,
    :data:`RX`, :data:`ODD`); dlc (int64); data (n, w) uint8 with ``length`` bytes used per row
    (zeros past them); channel (n,) objects (str, int or None); line (int64: line number in the
    file, 0 when unknown).
    """

    t_s: np.ndarray
    arbitration_id: np.ndarray
    flags: np.ndarray
    dlc: np.ndarray
    data: np.ndarray
    length: np.ndarray
    channel: np.ndarray
    line: np.ndarray

    def __len__(self) -> int:
        return len(self.t_s)

    @property
    def t_bus_ns(self) -> np.ndarray:
        """Timestamps as integer ns (``round(t_s * 1e9)``, as for a recorded frame)."""
        return np.rint(self.t_s * 1e9).astype(np.int64)

    def message(self, i: int) -> Any:
        """Frame ``i`` as a ``can.Message``."""
        import can

        f = int(self.flags[i])
        return can.Message(
            timestamp=float(self.t_s[i]),
            is_error_frame=bool(f & ERROR),
            arbitration_id=int(self.arbitration_id[i]),
            is_extended_id=bool(f & EXTENDED),
            is_remote_frame=bool(f & REMOTE),
            is_fd=bool(f & FD),
            is_rx=bool(f & RX),
            bitrate_switch=bool(f & BRS),
            error_state_indicator=bool(f & ESI),
            dlc=int(self.dlc[i]),
            data=None if f & REMOTE else bytearray(self.data[i, : self.length[i]].tobytes()),
            channel=self.channel[i],
        )

    def messages(self) -> list[Any]:
        return [self.message(i) for i in range(len(self))]

    def take(self, index: Any) -> FrameColumns:
        """The frames ``index`` (a slice, indexes or a mask)."""
        return FrameColumns(
            self.t_s[index], self.arbitration_id[index], self.flags[index], self.dlc[index],
            self.data[index], self.length[index], self.channel[index], self.line[index],
        )  # fmt: skip

    @staticmethod
    def from_messages(msgs: Sequence[Any], first_line: int = 0) -> FrameColumns:
        """Columns of ``can.Message`` objects (a live bus, python-can's readers); ``line``
        ``first_line, first_line + 1, ...`` (0: unknown)."""
        n = len(msgs)
        datas = [bytes(m.data) for m in msgs]
        length = np.fromiter(map(len, datas), np.int64, n)
        w = max(8, int(length.max()) if n else 0)
        if n and bool((length == w).all()):  # every frame of the widest length (8 bytes: usual)
            data = np.frombuffer(b"".join(datas), np.uint8).reshape(n, w).copy()
        else:
            data = np.frombuffer(b"".join(d.ljust(w, b"\0") for d in datas), np.uint8)
            data = data.reshape(n, w).copy()
        flags = np.fromiter(
            (
                EXTENDED * bool(m.is_extended_id) | ERROR * bool(m.is_error_frame)
                | REMOTE * bool(m.is_remote_frame) | FD * bool(m.is_fd)
                | BRS * bool(m.bitrate_switch) | ESI * bool(m.error_state_indicator)
                | RX * bool(m.is_rx)
                for m in msgs
            ),
            np.uint8,
            n,
        )  # fmt: skip
        ch = np.empty(n, object)
        ch[:] = [m.channel for m in msgs]
        return FrameColumns(
            np.fromiter((m.timestamp for m in msgs), np.float64, n),
            np.fromiter((m.arbitration_id for m in msgs), np.int64, n),
            flags,
            np.fromiter((m.dlc for m in msgs), np.int64, n),
            data,
            length,
            ch,
            np.arange(first_line, first_line + n, dtype=np.int64)
            if first_line
            else np.zeros(n, np.int64),
        )


def empty_frames(width: int = 8) -> FrameColumns:
    """No frames."""
    return FrameColumns(
        np.empty(0, np.float64), np.empty(0, np.int64), np.empty(0, np.uint8),
        np.empty(0, np.int64), np.empty((0, width), np.uint8), np.empty(0, np.int64),
        np.empty(0, object), np.empty(0, np.int64),
    )  # fmt: skip


def concat_frames(parts: Sequence[FrameColumns]) -> FrameColumns:
    """The frames of ``parts`` one after the other (data padded to the widest)."""
    if not parts:
        return empty_frames()
    if len(parts) == 1:
        return parts[0]
    w = max(p.data.shape[1] for p in parts)

    def cat(name: str) -> np.ndarray:
        return np.concatenate([getattr(p, name) for p in parts])

    data = np.concatenate([np.pad(p.data, ((0, 0), (0, w - p.data.shape[1]))) for p in parts])
    return FrameColumns(
        cat("t_s"), cat("arbitration_id"), cat("flags"), cat("dlc"), data, cat("length"),
        cat("channel"), cat("line"),
    )  # fmt: skip


def merge_by_line(a: FrameColumns, b: FrameColumns) -> FrameColumns:
    """The frames of ``a`` and ``b`` in line order."""
    both = concat_frames([a, b])
    return both.take(np.argsort(both.line, kind="stable"))
