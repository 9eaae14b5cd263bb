"""CAN log files read fast: candump ``-L`` ``.log`` files and Vector ASC ``.asc`` files parsed with
numpy, a block of lines at a time, into columns (:class:`FrameColumns`); every other format
python-can reads (BLF, TRC, ...) through python-can's own ``LogReader``, turned into the same
columns.

Both parsers give exactly what python-can's reader gives for each frame (the timestamp is the same
float: the text converted by the C library, like ``float()``), an order of magnitude faster.  They
read ``block_bytes`` of the file at a time (bounded memory).  A line they cannot parse raises
:class:`~cdpr.analysis.errors.ConfigError` naming the file and the line number (python-can stops
or skips silently on some of them); blank lines are skipped, as python-can does.  A timestamp
whose integer ns would not fit an int64 (after 2262) is an error in every format.  A candump block
whose lines all have one length and one layout (a load-cell log) is read by a fixed-width fast
path (:func:`_parse_fixed`, several times faster), any other by the general parser.

candump line layout (can-utils ``lib.c``): ``(<seconds>) <channel> <frame>[ R|T]``, frame
``<id>#<hex data>`` (classic), ``<id>#R[<dlc>]`` (remote), ``<id>##<flags><hex data>`` (CAN FD,
flags bit 0 bit-rate switch, bit 1 error-state indicator); an id of more than 3 hex digits is
extended (can-utils writes 3 or 8; python-can's writer writes other lengths for CAN FD, and its
reader reads 1-8); an id with the error flag 0x20000000 and the bus-error bit 0x80 is an error
frame.

ASC layout: see :func:`read_asc`.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cdpr.analysis.errors import ConfigError

#: flag bits of :attr:`FrameColumns.flags`; ODD: a frame a classic bus cannot carry as the log
#: gives it (an ASC line with a DLC past 15 or more than 8 bytes), read as python-can reads it
EXTENDED, ERROR, REMOTE, FD, BRS, ESI, RX, ODD = 1, 2, 4, 8, 16, 32, 64, 128

#: the largest timestamp (s) whose integer ns fits an int64 (the year 2262)
T_MAX_S = 9.2e9
_T_PROBLEM = "timestamp out of range (its integer ns would pass the year 2262)"

_CAN_ERR_FLAG = 0x20000000
_CAN_ERR_BUSERROR = 0x00000080

_HEX = np.full(256, 255, np.uint8)
for _i, _c in enumerate(b"0123456789abcdef"):
    _HEX[_c] = _i
for _i, _c in enumerate(b"ABCDEF"):
    _HEX[_c] = 10 + _i
#: control bytes no CAN log line holds (tab, carriage return and newline aside)
_CTRL = np.zeros(256, bool)
_CTRL[[*range(9), *range(11, 13), *range(14, 32), 127]] = True
_DEC = np.full(256, 255, np.uint8)
for _i, _c in enumerate(b"0123456789"):
    _DEC[_c] = _i


@dataclass
class FrameColumns:
    """A block of CAN frames as columns.

    t_s: timestamps (float64 s, as python-can gives them); arbitration_id (int64); flags (uint8:
    :data:`EXTENDED`, :data:`ERROR`, :data:`REMOTE`, :data:`FD`, :data:`BRS`, :data:`ESI`,
    :data:`RX`); dlc (int64); data (n, w) uint8 with ``length`` bytes used per row; channel (n,)
    objects (str, int or None); line (int64: line number in the file, 0 when unknown).
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

    @staticmethod
    def from_messages(msgs: list[Any], first_line: int = 0) -> FrameColumns:
        """Columns of ``can.Message`` objects (the fallback readers)."""
        n = len(msgs)
        w = max([8, *(len(m.data) for m in msgs)])
        data = np.zeros((n, w), np.uint8)
        length = np.zeros(n, np.int64)
        for i, m in enumerate(msgs):
            d = bytes(m.data)
            data[i, : len(d)] = np.frombuffer(d, np.uint8)
            length[i] = len(d)
        flags = np.array(
            [
                EXTENDED * bool(m.is_extended_id)
                | ERROR * bool(m.is_error_frame)
                | REMOTE * bool(m.is_remote_frame)
                | FD * bool(m.is_fd)
                | BRS * bool(m.bitrate_switch)
                | ESI * bool(m.error_state_indicator)
                | RX * bool(m.is_rx)
                for m in msgs
            ],
            np.uint8,
        )
        ch = np.empty(n, object)
        ch[:] = [m.channel for m in msgs]
        return FrameColumns(
            np.array([m.timestamp for m in msgs], np.float64),
            np.array([m.arbitration_id for m in msgs], np.int64),
            flags,
            np.array([m.dlc for m in msgs], np.int64),
            data,
            length,
            ch,
            np.arange(first_line, first_line + n, dtype=np.int64)
            if first_line
            else np.zeros(n, np.int64),
        )


def _next_at(positions: np.ndarray, after: np.ndarray) -> np.ndarray:
    """For each value of ``after``, the first of the sorted ``positions`` >= it (or a huge
    number)."""
    ext = np.append(positions, np.iinfo(np.int64).max // 2)
    return ext[np.searchsorted(positions, after)]


def _gather(buf: np.ndarray, start: np.ndarray, length: np.ndarray, width: int) -> np.ndarray:
    """(n, width) bytes ``buf[start : start + length]`` per row, left-aligned, zero-padded.

    Lines of one length (a log of one kind of frame) have their fields at evenly spaced starts:
    those are read through a strided view of the buffer instead of an index per byte."""
    n = len(start)
    step = int(start[1] - start[0]) if n > 1 else 1
    if (
        n > 1
        and step > 0
        and int(start[-1]) + width <= len(buf)
        and bool(np.all(np.diff(start) == step))
    ):
        out = np.lib.stride_tricks.as_strided(
            buf[int(start[0]) :], shape=(n, width), strides=(step, 1), writeable=False
        ).copy()
    else:
        idx = start[:, None] + np.arange(width)
        out = buf[np.minimum(idx, len(buf) - 1)]
    if not bool(np.all(length == width)):
        out[np.arange(width) >= length[:, None]] = 0
    return out


#: a candump line of the common layout (every line of a block alike: the fast path)
_FIXED_LINE = re.compile(
    rb"\(([0-9]+)\.([0-9]+)\) ([!-~]+) ([0-9A-Fa-f]{1,8})#((?:[0-9A-Fa-f]{2}){0,8})( [RrTt])?\n"
)
_PAIR = np.arange(1 << 16)
_PAIR_1ST, _PAIR_2ND = _PAIR & 0xFF, _PAIR >> 8  # two bytes read as a little-endian uint16
#: the value of two hex digits (0-255), 256 for anything else
_HEX2 = np.where(
    (_HEX[_PAIR_1ST] < 16) & (_HEX[_PAIR_2ND] < 16),
    _HEX[_PAIR_1ST].astype(np.uint16) * 16 + _HEX[_PAIR_2ND],
    256,
).astype(np.uint16)
#: the value of two decimal digits (0-99), 256 for anything else
_DEC2 = np.where(
    (_DEC[_PAIR_1ST] < 10) & (_DEC[_PAIR_2ND] < 10),
    _DEC[_PAIR_1ST].astype(np.uint16) * 10 + _DEC[_PAIR_2ND],
    256,
).astype(np.uint16)


def _pairs(rows: np.ndarray, start: int, stop: int, table: np.ndarray) -> np.ndarray:
    """``table`` of the byte pairs of columns ``start:stop`` of ``rows``: (n, ceil(width / 2));
    an odd width gets a leading '0'."""
    n, w = len(rows), stop - start
    c = np.empty((n, w + w % 2), np.uint8)
    c[:, : w % 2] = 48
    c[:, w % 2 :] = rows[:, start:stop]
    return table.take(c.view("<u2"))


def _parse_fixed(buf: np.ndarray, path: str, first_line: int) -> FrameColumns | None:
    """The frames of ``buf`` when every line has the layout and the length of the first one
    (``(<digits>.<digits>) <channel> <id>#<data>[ R|T]``: classic data frames of one id length,
    one data length, one channel, one direction token and timestamps of one digit count: a
    load-cell log), else None.

    The lines are the rows of a 2-D view of the block: each row must hold the first row's bytes
    at the fixed positions (punctuation, channel, direction token, newline) and decimal / hex
    digits at the others (read two at a time through 65536-entry tables), so that each row is one
    line the general parser (:func:`_parse_general`) reads into exactly these fields.  Anything
    else (another line, an error frame, a timestamp :func:`_fixed_timestamps` does not take or
    beyond :data:`T_MAX_S`) is None: the general parser then reads the block or names the bad
    line."""
    head = buf[:1024]
    nl = int(np.argmax(head == 10))
    if len(head) == 0 or head[nl] != 10:
        return None
    width = nl + 1
    m = _FIXED_LINE.fullmatch(bytes(buf[:width]))
    if m is None or len(buf) % width:
        return None
    a = buf.reshape(len(buf) // width, width)
    n = len(a)
    dot, rpar = m.end(1), m.end(2)
    id_s, id_e = m.span(4)
    d_s, d_e = m.span(5)
    # fixed bytes: '(', '.', ') <channel> ', '#', ' R|T' and the newline
    line0 = a[0]
    for s, e in ((0, 1), (dot, dot + 1), (rpar, id_s), (id_e, d_s), (d_e, width)):
        if not bool((a[:, s:e] == line0[s:e]).all()):
            return None
    ipart, fpart = _pairs(a, 1, dot, _DEC2), _pairs(a, dot + 1, rpar, _DEC2)
    data_hex = _pairs(a, d_s, d_e, _HEX2)
    id_hex = _HEX[a[:, id_s:id_e]]
    if max(int(ipart.max()), int(fpart.max()), int(data_hex.max(initial=0))) > 255:
        return None
    if int(id_hex.max()) > 15:
        return None
    t_s = _fixed_timestamps(ipart, fpart, dot - 1, rpar - dot - 1)
    if t_s is None or not bool((t_s < T_MAX_S).all()):
        return None
    idlen = id_e - id_s
    ids = np.zeros(n, np.int64)
    for c in range(idlen):
        ids = ids * 16 + id_hex[:, c]
    if bool((((ids & _CAN_ERR_FLAG) != 0) & ((ids & _CAN_ERR_BUSERROR) != 0)).any()):
        return None  # error frames: the general parser
    nbytes = data_hex.shape[1]
    data = np.zeros((n, 8), np.uint8)
    data[:, :nbytes] = data_hex
    name = m[3].decode("ascii")
    channel = np.empty(n, object)
    channel.fill(int(name) if name.isdigit() else name)
    rx = m[6] is None or m[6][1:] in (b"R", b"r")
    flags = np.full(n, EXTENDED * (idlen > 3) | RX * rx, np.uint8)
    return FrameColumns(
        t_s, ids & 0x1FFFFFFF, flags, np.full(n, nbytes, np.int64), data,
        np.full(n, nbytes, np.int64), channel,
        first_line + np.arange(n, dtype=np.int64),
    )  # fmt: skip


def _fixed_timestamps(ipairs: np.ndarray, fpairs: np.ndarray, ni: int, k: int) -> np.ndarray | None:
    """float64 of timestamps of ``ni`` integer and ``k`` fraction digits, given as two-digit
    values (0-99, a leading '0' for an odd count), exactly as ``float()`` converts the text, or
    None (more than 15 digits on a side; more than 15 in all with an integer part of 0 or of 2**40
    or more).

    The integer part I and the fraction F are matrix products: every product and partial sum is
    an integer below 2**53, exact in float64 in any summation order.  Up to 15 digits in all:
    N = I * 10**k + F is below 2**53 and N / 10**k (both exact) rounds as ``float()``, as in
    :func:`_timestamps`.  More digits: the value is rounded to 53 bits in integer arithmetic:
    with s = 53 - bit length of I, the mantissa M = round(N * 2**s / 10**k) = I * 2**s +
    round(F * 2**s / 10**k) (half to even) and the value M * 2**-s: the correctly rounded
    quotient, which is what ``float()`` gives."""
    if ni > 15 or k > 15:
        return None

    def value(pairs: np.ndarray) -> np.ndarray:
        p = pairs.shape[1]
        return pairs.astype(np.float64) @ np.array([100.0**j for j in range(p - 1, -1, -1)])

    ipart, frac = value(ipairs), value(fpairs)
    d = 10**k
    if ni + k <= 15:
        return (ipart * float(d) + frac) / float(d)
    ipart_i, frac_i = ipart.astype(np.int64), frac.astype(np.int64)
    lo, hi = int(ipart_i.min()), int(ipart_i.max())
    if lo < 1 or hi >= 1 << 40:
        return None
    if lo.bit_length() == hi.bit_length():  # one shift for the block (the usual case)
        s: Any = 53 - hi.bit_length()
    else:  # 53 - bit length of I
        s = 53 - np.frexp(ipart)[1].astype(np.int64)
    if d << (53 - lo.bit_length()) >= 1 << 61:  # F * 2**s and twice the remainder fit an int64
        return None
    scaled = frac_i << s
    q = scaled // d
    r2 = 2 * (scaled - q * d)
    mant = (ipart_i << s) + q
    mant += (r2 > d) | ((r2 == d) & ((mant & 1) == 1))
    return np.ldexp(mant.astype(np.float64), -s)


def _parse_block(buf: np.ndarray, path: str, first_line: int) -> FrameColumns:
    """Parse complete lines ``buf`` (ends with a newline) whose first line is ``first_line``: the
    fast path when all lines are alike (:func:`_parse_fixed`), else :func:`_parse_general`."""
    cols = _parse_fixed(buf, path, first_line)
    return cols if cols is not None else _parse_general(buf, path, first_line)


def _parse_general(buf: np.ndarray, path: str, first_line: int) -> FrameColumns:
    """Parse complete lines ``buf`` (ends with a newline) whose first line is ``first_line``."""
    _check_control_bytes(buf, path, first_line)
    nl = np.flatnonzero(buf == 10)
    starts = np.concatenate([[0], nl[:-1] + 1]).astype(np.int64)
    ends = nl.astype(np.int64)
    line_no = first_line + np.arange(len(starts), dtype=np.int64)
    # strip a carriage return and trailing blanks; skip blank lines (as python-can does)
    while True:
        last = buf[np.maximum(ends - 1, 0)]
        trim = (ends > starts) & ((last == 13) | (last == 32) | (last == 9))
        if not trim.any():
            break
        ends = ends - trim
    first = buf[np.minimum(starts, len(buf) - 1)]
    lead = (ends > starts) & ((first == 32) | (first == 9))
    while lead.any():
        starts = starts + lead
        first = buf[np.minimum(starts, len(buf) - 1)]
        lead = (ends > starts) & ((first == 32) | (first == 9))
    keep = ends > starts
    starts, ends, line_no = starts[keep], ends[keep], line_no[keep]
    n = len(starts)

    def bad(mask: np.ndarray, problem: str) -> None:
        if mask.any():
            i = int(np.flatnonzero(mask)[0])
            text = bytes(buf[starts[i] : ends[i]]).decode("latin-1")
            raise ConfigError(path, f"line {int(line_no[i])}", f"{problem}: {text[:80]!r}")

    if n == 0:
        return _empty()
    bad(buf[starts] != 40, "not a candump -L line (expected '(<seconds>) <channel> <id>#<data>')")
    rpar = _next_at(np.flatnonzero(buf == 41), starts)
    spaces = np.flatnonzero(buf == 32)
    sp1 = _next_at(spaces, rpar)
    sp2 = _next_at(spaces, sp1 + 1)
    bad((rpar >= ends) | (sp1 != rpar + 1) | (sp2 >= ends) | (sp2 == sp1 + 1),
        "not a candump -L line (expected '(<seconds>) <channel> <id>#<data>')")  # fmt: skip
    sp3 = _next_at(spaces, sp2 + 1)
    frame_end = np.minimum(sp3, ends)
    # an optional direction token ' R' / ' T' after the frame
    has_dir = sp3 < ends
    dir_char = buf[np.minimum(sp3 + 1, len(buf) - 1)] | 32  # lower case
    bad(has_dir & ((ends != sp3 + 2) | ((dir_char != ord("r")) & (dir_char != ord("t")))),
        "unexpected text after the frame (expected ' R' or ' T')")  # fmt: skip
    is_rx = ~has_dir | (dir_char == ord("r"))
    hashes = np.flatnonzero(buf == 35)
    h = _next_at(hashes, sp2 + 1)
    bad(h >= frame_end, "no '#' in the frame")

    # timestamp: the text between the parentheses, converted by the C library like float()
    tlen = rpar - starts - 1
    tw = int(tlen.max())
    ttext = _gather(buf, starts + 1, tlen, tw)
    bad(_bad_time_text(ttext, tlen), "bad timestamp (expected <digits>.<digits>)")
    t_s = _timestamps(ttext, tlen)
    if t_s is None:  # more than 15 digits
        t_s = ttext.view(f"S{tw}").ravel().astype(np.float64)
    bad(~(t_s < T_MAX_S), _T_PROBLEM)

    # id: hex digits between the second space and '#'
    idlen = h - sp2 - 1
    bad((idlen < 1) | (idlen > 8), "bad CAN id")
    idtext = _gather(buf, sp2 + 1, idlen, 8)
    idval = _HEX[idtext]
    bad(((idval == 255) & (np.arange(8) < idlen[:, None])).any(axis=1), "bad CAN id (not hex)")
    ids = np.zeros(n, np.int64)
    for c in range(8):
        use = c < idlen
        ids = np.where(use, ids * 16 + idval[:, c], ids)
    extended = idlen > 3

    # data: after '#': '#<flags>' for FD, 'R[<dlc>]' for remote, else hex pairs
    d0 = h + 1
    c0 = buf[np.minimum(d0, len(buf) - 1)]
    fd = (d0 < frame_end) & (c0 == 35)
    fdflags = np.where(fd, _HEX[buf[np.minimum(d0 + 1, len(buf) - 1)]], 0)
    bad(fd & ((d0 + 1 >= frame_end) | (fdflags == 255)), "bad CAN FD flags")
    dstart = np.where(fd, d0 + 2, d0)
    cs = buf[np.minimum(dstart, len(buf) - 1)] | 32
    remote = (dstart < frame_end) & (cs == ord("r"))
    dlen = np.maximum(frame_end - dstart, 0)
    rlen = np.where(remote, dlen - 1, 0)  # remote: optional decimal dlc
    rw = max(1, int(rlen.max()))
    rtext = _DEC[_gather(buf, dstart + 1, rlen, rw)]
    bad(remote & ((rtext == 255) & (np.arange(rw) < rlen[:, None])).any(axis=1), "bad remote dlc")
    rdlc = np.zeros(n, np.int64)
    for c in range(rw):
        rdlc = np.where(c < rlen, rdlc * 10 + rtext[:, c], rdlc)
    hexlen = np.where(remote, 0, dlen)
    bad((hexlen % 2 == 1) | (hexlen > 128), "bad data (expected up to 64 bytes as hex pairs)")
    bad(~fd & (hexlen > 16), "bad data (more than 8 bytes in a classic frame)")
    nbytes = hexlen // 2
    w = max(8, int(nbytes.max()))
    htext = _HEX[_gather(buf, dstart, hexlen, 2 * w)]
    bad(((htext == 255) & (np.arange(2 * w) < hexlen[:, None])).any(axis=1), "bad data (not hex)")
    htext[np.arange(2 * w) >= hexlen[:, None]] = 0
    data = (htext[:, 0::2] << 4) | htext[:, 1::2]
    dlc = np.where(remote, rdlc, nbytes)

    # channel: the text between the spaces (few distinct values); digits become an int
    clen = sp2 - sp1 - 1
    cw = int(clen.max())
    ctext = _gather(buf, sp1 + 1, clen, cw).view(f"S{cw}").ravel()
    uniq, inv = np.unique(ctext, return_inverse=True)
    names = [u.decode("latin-1") for u in uniq.tolist()]
    table = np.empty(len(names), object)
    table[:] = [int(s) if s.isdigit() else s for s in names]
    channel = table[inv.ravel()]

    error = ((ids & _CAN_ERR_FLAG) != 0) & ((ids & _CAN_ERR_BUSERROR) != 0)
    flags = (
        EXTENDED * extended
        | REMOTE * remote
        | FD * fd
        | BRS * (fd & ((fdflags & 1) != 0))
        | ESI * (fd & ((fdflags & 2) != 0))
        | RX * is_rx
    ).astype(np.uint8)
    ids = ids & 0x1FFFFFFF
    if error.any():  # python-can: Message(timestamp=..., is_error_frame=True), nothing else
        flags = np.where(error, ERROR | EXTENDED | RX, flags).astype(np.uint8)
        ids = np.where(error, 0, ids)
        dlc = np.where(error, 0, dlc)
        nbytes = np.where(error, 0, nbytes)
        data[error] = 0
        channel = channel.copy()
        channel[error] = None
    nbytes = np.where(remote, 0, nbytes)
    return FrameColumns(t_s, ids, flags, dlc.astype(np.int64), data, nbytes.astype(np.int64),
                        channel, line_no)  # fmt: skip


def _check_control_bytes(buf: np.ndarray, path: str, first_line: int) -> None:
    """A ConfigError naming the first line of ``buf`` that holds a control byte (a carriage return
    is one unless a newline follows it)."""
    cr = np.flatnonzero(buf == 13)
    lone_cr = cr[buf[np.minimum(cr + 1, len(buf) - 1)] != 10]  # a carriage return only before \n
    at = np.union1d(np.flatnonzero(_CTRL[buf]), lone_cr)
    if len(at):
        line = first_line + int(np.count_nonzero(buf[: at[0]] == 10))
        raise ConfigError(path, f"line {line}", f"control byte 0x{int(buf[at[0]]):02x} in the line")


def _bad_time_text(ttext: np.ndarray, tlen: np.ndarray) -> np.ndarray:
    """Rows of (n, w) texts that are not ``<digits>.<digits>`` (the form candump and Vector
    write; ``float()`` would also take exponents, signs, ``inf``...)."""
    inside = np.arange(ttext.shape[1]) < tlen[:, None]
    isdot = (ttext == 46) & inside
    ndig = np.count_nonzero((_DEC[ttext] != 255) & inside, axis=1)
    dot_at = np.argmax(isdot, axis=1)
    return (isdot.sum(axis=1) != 1) | (ndig != tlen - 1) | (dot_at == 0) | (dot_at == tlen - 1)


def _timestamps(ttext: np.ndarray, tlen: np.ndarray) -> np.ndarray | None:
    """float64 of decimal texts ``<digits>.<digits>`` (n, w) exactly as ``float()`` gives them, or
    None when a text is not of that form.  The digits make an integer N < 2**53 and the value is
    N / 10**k for k fraction digits: both exact in float64, so IEEE division rounds the quotient
    correctly, which is what ``float()`` does with the text."""
    n, w = ttext.shape
    inside = np.arange(w) < tlen[:, None]
    digit = _DEC[ttext]
    isdot = ttext == 46
    if not np.all(((digit != 255) | isdot) | ~inside):
        return None
    ndots = np.count_nonzero(isdot & inside, axis=1)
    if np.any(ndots > 1) or np.any(tlen - ndots > 15):  # N must stay below 2**53
        return None
    dotpos = np.where(ndots == 1, np.argmax(isdot, axis=1), tlen)
    k = np.where(ndots == 1, tlen - dotpos - 1, 0)
    N = np.zeros(n, np.int64)
    for c in range(w):
        use = inside[:, c] & ~isdot[:, c]
        N = np.where(use, N * 10 + digit[:, c], N)
    return N.astype(np.float64) / 10.0 ** k.astype(np.float64)


def _empty() -> FrameColumns:
    return FrameColumns(
        np.empty(0, np.float64), np.empty(0, np.int64), np.empty(0, np.uint8),
        np.empty(0, np.int64), np.empty((0, 8), np.uint8), np.empty(0, np.int64),
        np.empty(0, object), np.empty(0, np.int64),
    )  # fmt: skip


def read_candump(
    path: str | os.PathLike[str],
    block_bytes: int = 8 << 20,
    progress: Callable[[int], None] | None = None,
) -> Iterator[FrameColumns]:
    """The frames of a candump ``-L`` log, ``block_bytes`` of text at a time (``progress(bytes
    read)`` after each block)."""
    p = Path(path)
    line = 1
    with p.open("rb") as fh:
        for text in _line_blocks(fh, block_bytes, 0, progress):
            block = np.frombuffer(text, np.uint8)
            cols = _parse_block(block, str(p), line)
            line += int(np.count_nonzero(block == 10))
            if len(cols):
                yield cols


def _line_blocks(
    fh: Any, block_bytes: int, done: int, progress: Callable[[int], None] | None
) -> Iterator[bytes]:
    """Blocks of whole lines (each ending in a newline; a last line without one gets it) read
    ``block_bytes`` at a time from ``fh``; ``progress(bytes read, counting from done)`` after each
    read.  Blank trailing text is dropped."""
    rest = b""
    while True:
        chunk = fh.read(block_bytes)
        if not chunk:
            break
        done += len(chunk)
        if progress is not None:
            progress(done)
        text = rest + chunk
        cut = text.rfind(b"\n")
        if cut < 0:
            rest = text
            continue
        rest = text[cut + 1 :]
        yield text[: cut + 1]
    if rest.strip():
        yield rest + b"\n"


def _checked(cols: FrameColumns, path: Path, before: int) -> FrameColumns:
    """``cols`` (frames ``before + 1 ...`` of a log python-can read), or a ConfigError for a
    timestamp beyond :data:`T_MAX_S`."""
    late = np.flatnonzero(~(cols.t_s < T_MAX_S))
    if len(late):
        raise ConfigError(str(path), f"frame {before + int(late[0]) + 1}", _T_PROBLEM)
    return cols


def read_log(
    path: str | os.PathLike[str],
    block_frames: int = 100_000,
    progress: Callable[[int], None] | None = None,
) -> Iterator[FrameColumns]:
    """The frames of any CAN log: candump ``.log`` with :func:`read_candump`, other formats with
    python-can's ``LogReader`` (``block_frames`` at a time)."""
    p = Path(path)
    if p.suffix.lower() == ".log":
        yield from read_candump(p, progress=progress)
        return
    if p.suffix.lower() == ".asc":
        yield from read_asc(p, progress=progress)
        return
    import can

    reader = can.LogReader(str(p))
    count = 0
    try:
        block: list[Any] = []
        it = iter(reader)
        while True:
            try:
                m = next(it)
            except StopIteration:
                break
            except (
                Exception
            ) as exc:  # python-can raises what its parsers raise: never a silent stop
                raise ConfigError(
                    str(p), f"frame {count + 1}", f"python-can cannot read it: {exc}"
                ) from None
            count += 1
            block.append(m)
            if len(block) >= block_frames:
                yield _checked(FrameColumns.from_messages(block), p, count - len(block))
                block = []
        if block:
            yield _checked(FrameColumns.from_messages(block), p, count - len(block))
    finally:
        stop = getattr(reader, "stop", None)
        if stop is not None:
            stop()


# --- Vector ASC -----------------------------------------------------------------------------------

_DLC2LEN = np.array([0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64], np.int64)
_FD_LENGTHS = frozenset(_DLC2LEN.tolist())
_WS = np.zeros(256, bool)
_WS[[9, 13, 32]] = True  # tab, carriage return, space: other control bytes are errors
# python-can's header patterns, whitespace limited to spaces and tabs
_ASC_DATE = re.compile(r"date[ \t]+\w+[ \t]+(?P<datetime_string>.+)", re.IGNORECASE | re.ASCII)
_ASC_BASE = re.compile(
    r"base[ \t]+(?P<base>hex|dec)(?:[ \t]+timestamps[ \t]+(?P<ts>absolute|relative))?",
    re.IGNORECASE | re.ASCII,
)
_ASC_EVENTS = re.compile(
    r"(?P<no_events>no)?[ \t]*internal[ \t]+events[ \t]+logged", re.IGNORECASE | re.ASCII
)
_ASC_TIME = r"[0-9]+\.[0-9]+"
_S = r"[ \t]+"
#: lines python-can skips that a Vector log holds: comments, the trigger block, events (the
#: event texts as Vector writes them, case included)
_ASC_SKIP = re.compile(
    r"//.*|Begin[ \t]+Trigger[Bb]lock([ \t].*)?|End[ \t]+Trigger[Bb]lock|"
    + _ASC_TIME
    + _S
    + r"(Start of measurement|Stop of measurement|Log trigger event.*|CAN[ \t]+[0-9]+[ \t]+Status:.*"
    r"|[0-9]+[ \t]+(Statistic:|Status:|J1939TP[ \t]|SV:|TFS:|ErrorFrame([ \t]|$)).*"
    r"|CANFD[ \t]+[0-9]+[ \t]+(Rx|Tx)[ \t]+ErrorFrame([ \t].*)?|(SV|TFS):.*)",
    re.ASCII,
)
_ASC_ERROR = re.compile(_ASC_TIME + _S + r"[0-9]+" + _S + "ErrorFrame", re.ASCII)
_ASC_FD_ERROR = re.compile(_ASC_TIME + _S + "CANFD" + _S, re.ASCII)
_ASC_REMOTE = re.compile(
    _ASC_TIME + r"[ \t]+([0-9]+)[ \t]+(\w+)[ \t]+(Rx|Tx)[ \t]+r(?:[ \t]+([0-9]+))?"
    r"(?:[ \t]+\w+[ \t]*=.*)?",
    re.ASCII,
)
_ASC_FD = re.compile(
    _ASC_TIME + r"[ \t]+CANFD[ \t]+([0-9]+)[ \t]+(Rx|Tx)[ \t]+(\w+)(?:[ \t]+([!-~]+))??[ \t]+([01])"
    r"[ \t]+([01])[ \t]+([0-9A-Fa-f]{1,2})[ \t]+([0-9]+)((?:[ \t]+\w+)*)",
    re.ASCII,
)


@dataclass
class AscHeader:
    """What the header of an ASC file says (as python-can's ``ASCReader`` reads it)."""

    base: int  # 16 or 10
    timestamps: str | None  # 'absolute', 'relative' or None (no base line)
    body_offset: int  # byte offset of the first body line
    body_line: int  # its line number


def read_asc_header(path: str | os.PathLike[str]) -> AscHeader:
    """The header lines at the top of an ASC file: ``date``, ``base hex|dec [timestamps
    absolute|relative]``, comments, up to ``[no] internal events logged``."""
    base, ts, offset, line = 16, None, 0, 1
    with Path(path).open("rb") as fh:
        for raw in fh:
            try:
                text = raw.decode("utf-8").strip(" \t\r\n")
            except UnicodeDecodeError:
                raise ConfigError(str(path), f"line {line}", "not UTF-8 text") from None
            if _CTRL[np.frombuffer(raw, np.uint8)].any() or len(text.splitlines()) > 1:
                break  # not a header line: the body parser names it
            if _ASC_DATE.match(text) or text.startswith("//"):
                pass
            elif m := _ASC_BASE.match(text):
                base = 10 if m["base"].lower() == "dec" else 16
                ts = (m["ts"] or "absolute").lower()
            elif _ASC_EVENTS.match(text):
                offset, line = offset + len(raw), line + 1
                break
            else:
                break
            offset, line = offset + len(raw), line + 1
    return AscHeader(base, ts, offset, line)


def _tok_value(
    buf: np.ndarray, start: np.ndarray, length: np.ndarray, width: int, base: int
) -> tuple[np.ndarray, np.ndarray]:
    """Integer values of tokens of up to ``width`` digits in ``base`` and whether each is one."""
    n = len(start)
    if n == 0:
        return np.zeros(0, np.int64), np.ones(0, bool)
    table = _HEX if base == 16 else _DEC
    dig = table[_gather(buf, start, np.minimum(length, width), width)]
    inside = np.arange(width) < length[:, None]
    ok = (length >= 1) & (length <= width) & ~((dig == 255) & inside).any(axis=1)
    val = np.zeros(n, np.int64)
    for c in range(width):
        val = np.where(inside[:, c], val * base + dig[:, c], val)
    return val, ok


def _asc_block(buf: np.ndarray, path: str, first_line: int, base: int) -> FrameColumns:
    """Parse the complete body lines ``buf`` (ends with a newline) of an ASC file.

    Classic data frames (``<t> <ch> <id>[x] Rx|Tx d <dlc> <bytes> [Length = ...]``: the bulk of
    a log) are parsed with numpy from the positions of the whitespace-separated tokens; every
    other line (remote, error and CAN FD frames, events, comments) one at a time with the same
    rules as python-can's ``ASCReader``."""
    _check_control_bytes(buf, path, first_line)
    nl = np.flatnonzero(buf == 10).astype(np.int64)
    nlines = len(nl)
    if nlines == 0:
        return _empty()
    line_start = np.concatenate([[0], nl[:-1] + 1])
    sep = _WS[buf] | (buf == 10)
    prev_sep = np.concatenate([[True], sep[:-1]])
    next_sep = np.concatenate([sep[1:], [True]])
    tok_s = np.flatnonzero(~sep & prev_sep).astype(np.int64)
    tok_e = np.flatnonzero(~sep & next_sep).astype(np.int64) + 1
    if len(tok_s) == 0:  # blank lines only
        return _empty()
    tok_line = np.searchsorted(nl, tok_s)
    first_tok = np.searchsorted(tok_line, np.arange(nlines))
    ntok = np.bincount(tok_line, minlength=nlines)
    tok_len = tok_e - tok_s

    def tok(k: int, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """start and length of token ``k`` of lines ``rows`` (length 0 when missing)."""
        have = ntok[rows] > k
        i = np.where(have, first_tok[rows] + k, 0)
        return np.where(have, tok_s[i], 0), np.where(have, tok_len[i], 0)

    lines = np.arange(nlines)
    s4, l4 = tok(4, lines)
    s3, l3 = tok(3, lines)
    s1, l1 = tok(1, lines)
    c3 = _gather(buf, s3, np.minimum(l3, 2), 2)
    cand = (
        (ntok >= 6)
        & (l4 == 1)
        & (buf[s4] == ord("d"))
        & (l3 == 2)
        & ((c3[:, 0] == ord("R")) | (c3[:, 0] == ord("T")))
        & (c3[:, 1] == ord("x"))
        & (l1 >= 1)
        & (_DEC[buf[s1]] != 255)
    )
    rows = np.flatnonzero(cand)
    # a frame line is ASCII (Vector's attributes after the bytes included)
    non_ascii = np.zeros(nlines, bool)
    non_ascii[np.searchsorted(nl, np.flatnonzero(buf >= 128))] = True

    def bad(mask: np.ndarray, problem: str) -> None:
        if mask.any():
            r = int(rows[int(np.flatnonzero(mask)[0])])
            text = bytes(buf[line_start[r] : nl[r]]).decode("latin-1").strip()
            raise ConfigError(path, f"line {first_line + r}", f"{problem}: {text[:80]!r}")

    n = len(rows)
    s0, l0 = tok(0, rows)
    tw = max(1, int(l0.max())) if n else 1
    ttext = _gather(buf, s0, l0, tw)
    bad(_bad_time_text(ttext, l0), "bad timestamp (expected <digits>.<digits>)")
    t_s = _timestamps(ttext, l0)
    if t_s is None:
        t_s = ttext.view(f"S{tw}").ravel().astype(np.float64)
    bad(~(t_s < T_MAX_S), _T_PROBLEM)
    ch, ok = _tok_value(buf, *tok(1, rows), 6, 10)
    bad(~ok, "bad channel")
    bad(non_ascii[rows], "not ASCII text in a frame line")
    s2, l2 = tok(2, rows)
    ext = (l2 >= 2) & ((buf[s2 + l2 - 1] | 32) == ord("x"))
    ids, ok = _tok_value(buf, s2, l2 - ext, 8 if base == 16 else 10, base)
    bad(~ok, "bad CAN id")
    bad(ids > np.where(ext, 0x1FFFFFFF, 0x7FF), "CAN id out of range")
    dlc_raw, ok = _tok_value(buf, *tok(5, rows), 2, base)
    bad(~ok, "bad DLC")
    # python-can: the length of the DLC (64 past 15), at most 8 bytes of a classic frame read
    dlc = np.where(dlc_raw > 15, 64, _DLC2LEN[np.minimum(dlc_raw, 15)])
    nbytes = np.minimum(dlc, 8)
    bad(ntok[rows] < 6 + nbytes, "fewer data bytes than the DLC says")
    data = np.zeros((n, 8), np.uint8)
    bw = 2 if base == 16 else 3
    for k in range(8):
        use = k < nbytes
        sk, lk = tok(6 + k, rows)
        v, ok = _tok_value(buf, sk, lk, bw, base)
        if base == 16:
            ok &= lk == 2
        bad(use & (~ok | (v > 255)), f"bad data byte {k + 1}")
        data[:, k] = np.where(use, v, 0)
    # a DLC above 8 may carry up to its length in bytes: python-can keeps the first 8
    extra = _extra_bytes(buf, tok, rows, dlc - nbytes, base)
    used = nbytes + extra
    # after the bytes: nothing, or Vector's attributes ("Length = 244016 BitCount = 125 ...")
    more = ntok[rows] > 6 + used
    i_eq = np.minimum(np.where(more, first_tok[rows] + 7 + used, 0), len(tok_s) - 1)
    eq_ok = (ntok[rows] > 7 + used) & (tok_len[i_eq] == 1) & (buf[tok_s[i_eq]] == ord("="))
    bad(more & ~eq_ok, "unexpected text after the data bytes")
    rx = c3[rows, 0] == ord("R")
    # a frame no classic bus carries (a DLC past 15, bytes past the 8th): read, flagged ODD
    odd = (dlc_raw > 15) | (extra > 0)
    fast = FrameColumns(
        t_s, ids, (EXTENDED * ext | RX * rx | ODD * odd).astype(np.uint8), dlc, data, nbytes,
        np.asarray(ch - 1, object), first_line + rows,
    )  # fmt: skip

    # every other line: python-can's rules, one line at a time (rare in a load-cell log)
    other = np.flatnonzero(~cand)
    slow: list[Any] = []
    slow_lines: list[int] = []
    for r in other.tolist():
        text = bytes(buf[line_start[r] : nl[r]]).decode("utf-8", "replace").strip(" \t\r")
        if not text:
            continue
        msg = _asc_slow_line(text, base, path, first_line + r)
        if msg is not None:
            slow.append(msg)
            slow_lines.append(first_line + r)
    if not slow:
        return fast
    sc = FrameColumns.from_messages(slow)
    sc.line = np.array(slow_lines, np.int64)
    return _merge_by_line(fast, sc)


def _extra_bytes(
    buf: np.ndarray,
    tok: Callable[[int, np.ndarray], tuple[np.ndarray, np.ndarray]],
    rows: np.ndarray,
    room: np.ndarray,
    base: int,
) -> np.ndarray:
    """How many data bytes follow the first 8 of each classic frame line (up to ``room``, what
    its DLC's length leaves: a line of Vector's ``d 40`` with 64 bytes)."""
    extra = np.zeros(len(rows), np.int64)
    live = np.flatnonzero(room > 0)
    k = 0
    while len(live):
        sk, lk = tok(14 + k, rows[live])
        v, ok = _tok_value(buf, sk, lk, 2 if base == 16 else 3, base)
        ok &= (lk == 2) if base == 16 else (v <= 255)
        live = live[ok]
        extra[live] += 1
        k += 1
        live = live[room[live] > k]
    return extra


def _asc_slow_line(text: str, base: int, path: str, line: int) -> Any:
    """One ASC line that is not a classic data frame: a ``can.Message`` (remote, error and CAN FD
    frames, made by python-can's ``ASCReader``) or None (an event or a comment python-can skips);
    anything else is a ConfigError naming the line."""
    import io

    import can.io.asc as asc

    def fail(problem: str) -> None:
        raise ConfigError(path, f"line {line}", f"{problem}: {text[:80]!r}")

    if len(text.splitlines()) > 1:
        fail("a line break character inside the line")
    t0 = re.match(_ASC_TIME + r"(?=[ \t]|$)", text)
    if t0 is not None and not float(t0[0]) < T_MAX_S:
        fail(_T_PROBLEM)
    reader = asc.ASCReader(io.StringIO(""), base="dec" if base == 10 else "hex")
    digits = r"[0-9]" if base == 10 else r"[0-9A-Fa-f]"
    if m := _ASC_REMOTE.fullmatch(text):
        ts, ch, rest = text.split(None, 2)
        if not re.fullmatch(digits + r"{1,10}[xX]?", m[2]):
            fail("bad CAN id")
        return reader._process_classic_can_frame(
            rest, {"timestamp": float(ts), "channel": int(ch) - 1}
        )
    if _ASC_SKIP.fullmatch(text):
        if _ASC_ERROR.match(text):
            ts, ch, rest = text.split(None, 2)
            kw = {"timestamp": float(ts), "channel": int(ch) - 1}
            return reader._process_classic_can_frame(rest, kw)
        if _ASC_FD_ERROR.match(text):
            ts, _, rest = text.split(None, 2)
            return reader._process_fd_can_frame(rest, {"timestamp": float(ts), "is_fd": True})
        return None
    if m := _ASC_FD.fullmatch(text):
        if not re.fullmatch(digits + r"{1,10}[xX]?", m[3]):
            fail("bad CAN id")
        dlc = int(m[7], base) if re.fullmatch(digits + "+", m[7]) else 99
        length = int(m[8])
        tokens = m[9].split()
        if dlc > 15 or length not in _FD_LENGTHS or (length and int(_DLC2LEN[dlc]) != length):
            fail("CAN FD DLC and data length disagree")
        if len(tokens) < length or not all(
            re.fullmatch(digits + (r"{2}" if base == 16 else r"{1,3}"), b) and int(b, base) < 256
            for b in tokens[:length]
        ):
            fail("bad CAN FD data bytes")
        ts, _, rest = text.split(None, 2)
        return reader._process_fd_can_frame(rest, {"timestamp": float(ts), "is_fd": True})
    fail("not an ASC frame, event or comment line")
    return None


def _merge_by_line(a: FrameColumns, b: FrameColumns) -> FrameColumns:
    """The frames of ``a`` and ``b`` in line order."""
    line = np.concatenate([a.line, b.line])
    order = np.argsort(line, kind="stable")
    w = max(a.data.shape[1], b.data.shape[1])

    def pad(d: np.ndarray) -> np.ndarray:
        return np.pad(d, ((0, 0), (0, w - d.shape[1])))

    return FrameColumns(
        np.concatenate([a.t_s, b.t_s])[order],
        np.concatenate([a.arbitration_id, b.arbitration_id])[order],
        np.concatenate([a.flags, b.flags])[order],
        np.concatenate([a.dlc, b.dlc])[order],
        np.concatenate([pad(a.data), pad(b.data)])[order],
        np.concatenate([a.length, b.length])[order],
        np.concatenate([a.channel, b.channel])[order],
        line[order],
    )


def _check_utf8(text: bytes, path: str, first_line: int) -> None:
    """python-can reads an ASC file as text: a byte sequence that is not UTF-8 is an error."""
    try:
        text.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = first_line + text.count(b"\n", 0, exc.start)
        raise ConfigError(path, f"line {line}", "not UTF-8 text") from None


def read_asc(
    path: str | os.PathLike[str],
    block_bytes: int = 8 << 20,
    progress: Callable[[int], None] | None = None,
) -> Iterator[FrameColumns]:
    """The frames of a Vector ASC log, ``block_bytes`` of text at a time, equal field by field to
    python-can's ``LogReader`` (its ``ASCReader``: timestamps as written, channel ``n - 1``).

    The header (``date``, ``base hex|dec [timestamps absolute|relative]``, comments, ``[no]
    internal events logged``) is read as python-can reads it; ``base dec`` makes ids, DLCs and
    data decimal.  Classic data frames ``<t> <ch> <id>[x] Rx|Tx d <dlc> <bytes> [Length = ...]``
    (the bulk of a log) are parsed with numpy; remote frames, error frames (classic and CAN FD),
    CAN FD frames (``<t> CANFD <ch> Rx|Tx <id>[x] [<name>] <brs> <esi> <dlc> <length> <bytes>
    ...``) are recognised line by line and made into messages by python-can's ``ASCReader`` (so
    they are as python-can reads them; a log of many CAN FD frames reads at python-can's speed).
    Skipped, as python-can skips them: blank lines, ``//`` comments, ``Begin/End Triggerblock``
    and the events Vector writes (``Start of measurement``, ``CAN n Status:``, ``n Statistic:``,
    ``n J1939TP``, ``Log trigger event``, ...).  Stricter than python-can (each a ConfigError
    naming the file and line): any other line, a frame with fewer data bytes than its DLC, text
    after the bytes that is not Vector's ``Name = value`` attributes, a byte not of two hex digits
    (hex base), a standard id above 0x7FF or an extended one above 0x1FFFFFFF, a CAN FD DLC that
    disagrees with the length, text that is not UTF-8.  One difference the other way round:
    python-can drops the first line after a header that does not end with ``internal
    events logged``; this parser reads it."""
    p = Path(path)
    head = read_asc_header(p)
    line = head.body_line
    with p.open("rb") as fh:
        fh.seek(head.body_offset)
        for text in _line_blocks(fh, block_bytes, head.body_offset, progress):
            _check_utf8(text, str(p), line)
            block = np.frombuffer(text, np.uint8)
            cols = _asc_block(block, str(p), line, head.base)
            line += int(np.count_nonzero(block == 10))
            if len(cols):
                yield cols
