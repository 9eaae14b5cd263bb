"""PEAK TRC logs (``.trc``) parsed with numpy into :class:`~cdpr.daq.can_frames.FrameColumns`, equal
field by field to python-can's ``TRCReader``, versions 1.0 to 2.1.

The header (``;``-lines) gives ``$FILEVERSION`` (1.1, 1.3, 2.0, 2.1; anything else is read as
1.0, as python-can does), ``$STARTTIME`` (days since 1899-12-30; the frames' offsets are added to
it) and, from 2.0 on, ``$COLUMNS`` (the order of the fields of a line).  Body lines, as python-can
reads them (``O``: the offset in ms, ``float(text) / 1000 + start``):

- 1.0: ``N) O ID DLC data|RTR`` (channel 1, received; an id ``FFFFFFFF`` is a bus-status line,
  dropped);
- 1.1: ``N) O Rx|Tx ID DLC data|RTR`` (channel 1);
- 1.3: ``N) O BUS Rx|Tx ID - DLC data|RTR``;
- 2.x: the ``$COLUMNS`` fields (``T`` the type: ``DT``, ``RR`` remote, ``FD``, ``FB`` (bit-rate
  switch), ``FE`` (BRS + error state), ``BI`` (error state); ``I`` id, ``d`` Rx|Tx, ``B`` bus,
  ``l`` data length or ``L`` DLC, ``D`` the data bytes, the rest of the line).

An id of more than 4 hex digits is extended.  Lines of other types (status, warnings, error
counters, ...) are skipped, as python-can skips them.  A line of a frame type that does not have
its fields (python-can skips it with a warning, or raises) is a ConfigError naming the file and
the line; blank and ``;`` lines are skipped.
"""

from __future__ import annotations

import datetime
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cdpr.analysis.errors import ConfigError

from .can_frames import (
    BRS,
    ESI,
    EXTENDED,
    FD,
    REMOTE,
    RX,
    T_MAX_S,
    T_PROBLEM,
    FrameColumns,
    empty_frames,
)
from .canlog_text import (
    DEC,
    HEX,
    LineTokens,
    check_control_bytes,
    check_utf8,
    gather,
    line_blocks,
    timestamps,
    tok_value,
)

_CAN_FD_DLC = (0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64)
#: python-can's ``len2dlc``: the DLC of a data length
_LEN2DLC = np.array([next((d for d, n in enumerate(_CAN_FD_DLC) if n >= k), 15) if k > 8 else k
                     for k in range(256)], np.int64)  # fmt: skip
_FRAME_TYPES_V2 = (b"DT", b"FD", b"FB", b"FE", b"BI", b"RR")


@dataclass
class TrcHeader:
    """What the ``;``-lines at the top of a TRC file say (as python-can's ``TRCReader`` reads
    them) and where the body starts."""

    version: str  # "1.0" (also for an unknown version), "1.1", "1.3", "2.0", "2.1"
    start_s: float
    columns: dict[str, int]
    body_offset: int
    body_line: int


def read_trc_header(path: str | os.PathLike[str]) -> TrcHeader:
    version, start, columns = "1.0", 0.0, {}
    offset, line = 0, 1
    with Path(path).open("rb") as fh:
        for raw in fh:
            text = raw.decode("utf-8", "replace").strip()
            if not text.startswith(";"):
                break
            try:
                if text.startswith(";$FILEVERSION"):
                    v = text.split("=")[1]
                    version = v if v in ("1.1", "1.3", "2.0", "2.1") else "1.0"
                elif text.startswith(";$STARTTIME"):
                    start = (
                        datetime.datetime(1899, 12, 30, tzinfo=datetime.UTC)
                        + datetime.timedelta(days=float(text.split("=")[1]))
                    ).timestamp()
                elif text.startswith(";$COLUMNS"):
                    names = text.split("=")[1].split(",")
                    columns = {c: names.index(c) for c in names}
            except (IndexError, ValueError, OverflowError):
                raise ConfigError(str(path), f"line {line}", f"bad header line: {text!r}") from None
            offset, line = offset + len(raw), line + 1
    if version >= "2.0" and not columns:
        raise ConfigError(str(path), "", f"a TRC {version} file without its $COLUMNS line")
    return TrcHeader(version, start, columns, offset, line)


def read_trc(
    path: str | os.PathLike[str],
    progress: Callable[[int], None] | None = None,
    block_bytes: int = 8 << 20,
) -> Iterator[FrameColumns]:
    """The frames of a PEAK TRC log (see the module docstring), ``block_bytes`` of text at a
    time."""
    p = Path(path)
    head = read_trc_header(p)
    layout = _layout(head, str(p))
    line = head.body_line
    with p.open("rb") as fh:
        fh.seek(head.body_offset)
        for text in line_blocks(fh, block_bytes, head.body_offset, progress):
            check_utf8(text, str(p), line)
            block = np.frombuffer(text, np.uint8)
            cols = _block(block, str(p), line, head, layout)
            line += int(np.count_nonzero(block == 10))
            if len(cols):
                yield cols


@dataclass
class _Layout:
    """Token indexes of a version's fields (-1: absent); ``data`` the first data token."""

    time: int
    type: int
    ident: int
    dlc: int
    length: int  # 2.x ``l``: a data length (the DLC is its len2dlc)
    bus: int
    direction: int
    data: int
    last: int  # the index of the last field (the rest of the line; 2.x)


def _layout(head: TrcHeader, path: str) -> _Layout:
    if head.version == "1.0":
        return _Layout(1, -1, 2, 3, -1, -1, -1, 4, -1)
    if head.version == "1.1":
        return _Layout(1, 2, 3, 4, -1, -1, 2, 5, -1)
    if head.version == "1.3":
        return _Layout(1, 3, 4, 6, -1, 2, 3, 7, -1)
    c = head.columns
    for need in ("O", "T", "I", "d"):
        if need not in c:
            raise ConfigError(path, "$COLUMNS", f"no {need} column")
    if "l" not in c and "L" not in c:
        raise ConfigError(path, "$COLUMNS", "no length (l) or DLC (L) column")
    return _Layout(
        c["O"], c["T"], c["I"], c.get("L", -1), c.get("l", -1), c.get("B", -1), c["d"],
        c.get("D", -1), len(c) - 1,
    )  # fmt: skip


def _code(word: bytes) -> int:
    return int.from_bytes(word, "little")


def _codes(buf: np.ndarray, start: np.ndarray, length: np.ndarray, width: int) -> np.ndarray:
    """The first ``width`` (<= 8) bytes of tokens as little-endian integers (0 past a token's
    length; a longer token gets -1): tokens compared with words in one integer comparison."""
    out = np.zeros(start.shape, np.int64)
    for j in range(width - 1, -1, -1):
        out = (out << 8) | np.where(j < length, buf[np.minimum(start + j, len(buf) - 1)], 0)
    return np.where(length > width, -1, out)


def _block(
    buf: np.ndarray, path: str, first_line: int, head: TrcHeader, lay: _Layout
) -> FrameColumns:
    check_control_bytes(buf, path, first_line)
    lt = LineTokens.of(buf)
    if lt is None:
        return empty_frames()
    rows = np.flatnonzero(lt.ntok > 0)
    rows = rows[buf[lt.tok_s[lt.first_tok[rows]]] != ord(";")]  # comment lines

    def bad(mask: np.ndarray, problem: str) -> None:
        if mask.any():
            r = int(rows[int(np.flatnonzero(mask)[0])])
            raise ConfigError(path, f"line {first_line + r}", f"{problem}: {lt.text(r)[:80]!r}")

    v2 = head.version >= "2.0"
    if lay.type >= 0:  # frames of a type python-can reads; the others skipped
        s, n_ = lt.tok(lay.type, rows)
        t = _codes(buf, s, n_, 2)
        types = (b"Rx", b"Tx") if not v2 else _FRAME_TYPES_V2
        rows = rows[np.isin(t, [_code(w) for w in types])]
    need = max(lay.time, lay.ident, lay.dlc, lay.length, lay.bus, lay.direction) + 1
    k = max(need, lay.data + 1 if lay.data >= 0 else 0)
    ts_, tl_ = lt.matrix(rows, k)
    bad(lt.ntok[rows] < need, "fewer fields than a frame line has")
    if head.version == "1.0":  # a bus-status line: id FFFFFFFF
        keep = _codes(buf, ts_[:, lay.ident], tl_[:, lay.ident], 8) != _code(b"FFFFFFFF")
        rows, ts_, tl_ = rows[keep], ts_[keep], tl_[keep]
    n = len(rows)
    if n == 0:
        return empty_frames()
    # the offset in ms: float(text) / 1000 (+ the start time from 1.1 on)
    tl = tl_[:, lay.time]
    tw = int(tl.max())
    ttext = gather(buf, ts_[:, lay.time], tl, tw)
    inside = np.arange(tw) < tl[:, None]
    dig = (DEC[ttext] != 255) & inside
    dots = (ttext == 46) & inside
    bad(((dig | dots).sum(axis=1) != tl) | (dots.sum(axis=1) > 1) | ~dig[:, 0], "bad time offset")
    off = timestamps(ttext, tl)
    if off is None:
        off = ttext.view(f"S{tw}").ravel().astype(np.float64)
    t_s = off / 1000 + (head.start_s if head.version != "1.0" else 0)
    bad(~(t_s < T_MAX_S), T_PROBLEM)
    ids, ok = tok_value(buf, ts_[:, lay.ident], tl_[:, lay.ident], 8, 16)
    bad(~ok, "bad CAN id")
    ext = tl_[:, lay.ident] > 4
    if lay.length >= 0:
        length_text, ok = tok_value(buf, ts_[:, lay.length], tl_[:, lay.length], 3, 10)
        bad(~ok | (length_text > 255), "bad data length")
        dlc = _LEN2DLC[np.minimum(length_text, 255)]
    else:
        dlc, ok = tok_value(buf, ts_[:, lay.dlc], tl_[:, lay.dlc], 3, 10)
        bad(~ok, "bad DLC")
    if lay.bus >= 0:
        bus, ok = tok_value(buf, ts_[:, lay.bus], tl_[:, lay.bus], 9, 10)
        bad(~ok, "bad bus number")
    else:
        bus = np.ones(n, np.int64)
    if lay.direction >= 0:
        d = lay.direction
        rx = _codes(buf, ts_[:, d], tl_[:, d], 2) == _code(b"Rx")
    else:
        rx = np.ones(n, bool)
    flags = EXTENDED * ext | RX * rx
    if v2:
        t = _codes(buf, ts_[:, lay.type], tl_[:, lay.type], 2)
        remote, fd, fb, fe, bi = (t == _code(w) for w in (b"RR", b"FD", b"FB", b"FE", b"BI"))
        flags = (flags | REMOTE * remote | FD * (fd | fb | fe | bi) | BRS * (fb | fe)
                 | ESI * (fe | bi))  # fmt: skip
        data, length = _data_v2(buf, lt, rows, lay, np.where(remote, 0, dlc), bad)
    else:
        has = lt.ntok[rows] > lay.data
        remote = has & (_codes(buf, ts_[:, lay.data], tl_[:, lay.data], 3) == _code(b"RTR"))
        flags = flags | REMOTE * remote
        data, length = _data_v1(buf, lt, rows, lay, np.where(remote, 0, dlc), bad)
    ch = np.empty(n, object)
    ch[:] = bus.tolist()
    return FrameColumns(
        t_s, ids, flags.astype(np.uint8), dlc.astype(np.int64), data, length, ch,
        first_line + rows,
    )  # fmt: skip


def _data_v1(buf, lt, rows, lay, nbytes, bad):  # noqa: ANN001, ANN202
    """1.x: ``nbytes`` data tokens of one or two hex digits (python-can's ``int(token, 16)``)."""
    n = len(rows)
    bad(lt.ntok[rows] < lay.data + nbytes, "fewer data bytes than the DLC says")
    w = int(nbytes.max()) if n else 0
    data = np.zeros((n, max(8, w)), np.uint8)
    if w:
        s, ln = lt.matrix(rows, lay.data + w)
        s, ln = s[:, lay.data :], ln[:, lay.data :]
        use = np.arange(w) < nbytes[:, None]
        hi = HEX[buf[s]]
        lo = HEX[buf[np.minimum(s + 1, len(buf) - 1)]]
        two = ln == 2
        bad((use & ~((ln == 1) | two)).any(axis=1), "bad data byte")
        val = np.where(two, hi.astype(np.int64) * 16 + lo, hi)
        bad((use & ((hi > 15) | (two & (lo > 15)))).any(axis=1), "bad data byte (not hex)")
        data[:, :w] = np.where(use, val, 0)
    return data, nbytes.astype(np.int64)


def _data_v2(buf, lt, rows, lay, dlc, bad):  # noqa: ANN001, ANN202
    """2.x: the ``D`` field (the rest of the line when it is the last column) as hex bytes
    (python-can's ``bytearray.fromhex``), when the DLC is not 0 and the frame not remote."""
    n = len(rows)
    want = dlc > 0
    if lay.data < 0:
        bad(want, "no data column (D)")
        return np.zeros((n, 8), np.uint8), np.zeros(n, np.int64)
    ntok = lt.ntok[rows]
    last = lay.data == lay.last
    count = np.where(want, np.maximum(ntok - lay.data, 0) if last else (ntok > lay.data), 0)
    bad(want & (count == 0), "no data bytes")
    maxc = int(count.max()) if n else 0
    if not maxc:
        return np.zeros((n, 8), np.uint8), np.zeros(n, np.int64)
    s, ln = lt.matrix(rows, lay.data + maxc)
    s, ln = s[:, lay.data :], ln[:, lay.data :]
    use = np.arange(maxc) < count[:, None]
    ln = np.where(use, ln, 0)
    bad((ln % 2 != 0).any(axis=1), "bad data (expected pairs of hex digits)")
    length = (ln // 2).sum(axis=1)
    if bool((ln[use] == 2).all()):  # one byte a token (the usual layout): at once
        hi, lo = HEX[buf[s]], HEX[buf[np.minimum(s + 1, len(buf) - 1)]]
        bad((use & ((hi > 15) | (lo > 15))).any(axis=1), "bad data (not hex)")
        data = np.zeros((n, max(8, maxc)), np.uint8)
        data[:, :maxc] = np.where(use, hi.astype(np.uint8) << 4 | lo.astype(np.uint8), 0)
        return data, length.astype(np.int64)
    data = np.zeros((n, max(8, int(length.max()))), np.uint8)  # tokens of several bytes
    for i in np.flatnonzero(length).tolist():
        text = " ".join(bytes(buf[a : a + b]).decode("latin-1") for a, b in zip(
            s[i].tolist(), ln[i].tolist(), strict=True) if b)  # fmt: skip
        try:
            d = bytes.fromhex(text)
        except ValueError:
            bad(np.arange(n) == i, "bad data (not hex)")
            raise
        data[i, : len(d)] = np.frombuffer(d, np.uint8)
    return data, length.astype(np.int64)
