"""candump ``-L`` logs (``.log``) parsed with numpy, a block of lines at a time, into
:class:`~cdpr.daq.can_frames.FrameColumns` equal field by field to python-can's
``CanutilsLogReader`` (the timestamp is the same float: the text converted as ``float()`` does),
an order of magnitude faster.  A block whose lines all have one length and one layout (a load-cell
log) is read by a fixed-width fast path (:func:`_parse_fixed`, several times faster), any other
by the general parser.  A line they cannot parse raises
:class:`~cdpr.analysis.errors.ConfigError` naming the file and the line number (python-can stops
or skips silently on some of them); blank lines are skipped, as python-can does; a timestamp whose
integer ns would not fit an int64 (after 2262) is an error.

Line layout (can-utils ``lib.c``): ``(<seconds>) <channel> <frame>[ R|T]``, frame
``<id>#<hex data>`` (classic), ``<id>#R[<dlc>]`` (remote), ``<id>##<flags><hex data>`` (CAN FD,
flags bit 0 bit-rate switch, bit 1 error-state indicator); an id of more than 3 hex digits is
extended (can-utils writes 3 or 8; python-can's writer writes other lengths for CAN FD, and its
reader reads 1-8); an id with the error flag 0x20000000 and the bus-error bit 0x80 is an error
frame.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from cdpr.analysis.errors import ConfigError

from .can_frames import (
    BRS,
    ERROR,
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
    DEC2,
    HEX,
    HEX2,
    bad_time_text,
    check_control_bytes,
    fixed_timestamps,
    gather,
    line_blocks,
    next_at,
    pairs,
    timestamps,
)

_CAN_ERR_FLAG = 0x20000000
_CAN_ERR_BUSERROR = 0x00000080


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
        for text in line_blocks(fh, block_bytes, 0, progress):
            block = np.frombuffer(text, np.uint8)
            cols = _parse_block(block, str(p), line)
            line += int(np.count_nonzero(block == 10))
            if len(cols):
                yield cols


#: a candump line of the common layout (every line of a block alike: the fast path)
_FIXED_LINE = re.compile(
    rb"\(([0-9]+)\.([0-9]+)\) ([!-~]+) ([0-9A-Fa-f]{1,8})#((?:[0-9A-Fa-f]{2}){0,8})( [RrTt])?\n"
)


def _parse_fixed(buf: np.ndarray, path: str, first_line: int) -> FrameColumns | None:
    """The frames of ``buf`` when every line has the layout and the length of the first one
    (``(<digits>.<digits>) <channel> <id>#<data>[ R|T]``: classic data frames of one id length,
    one data length, one channel, one direction token and timestamps of one digit count: a
    load-cell log), else None.

    The lines are the rows of a 2-D view of the block: each row must hold the first row's bytes
    at the fixed positions (punctuation, channel, direction token, newline) and decimal / hex
    digits at the others (read two at a time through 65536-entry tables), so that each row is one
    line the general parser (:func:`_parse_general`) reads into exactly these fields.  Anything
    else (another line, an error frame, a timestamp :func:`fixed_timestamps` does not take or
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
    ipart, fpart = pairs(a, 1, dot, DEC2), pairs(a, dot + 1, rpar, DEC2)
    data_hex = pairs(a, d_s, d_e, HEX2)
    id_hex = HEX[a[:, id_s:id_e]]
    if max(int(ipart.max()), int(fpart.max()), int(data_hex.max(initial=0))) > 255:
        return None
    if int(id_hex.max()) > 15:
        return None
    t_s = fixed_timestamps(ipart, fpart, dot - 1, rpar - dot - 1)
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


def _parse_block(buf: np.ndarray, path: str, first_line: int) -> FrameColumns:
    """Parse complete lines ``buf`` (ends with a newline) whose first line is ``first_line``: the
    fast path when all lines are alike (:func:`_parse_fixed`), else :func:`_parse_general`."""
    cols = _parse_fixed(buf, path, first_line)
    return cols if cols is not None else _parse_general(buf, path, first_line)


def _parse_general(buf: np.ndarray, path: str, first_line: int) -> FrameColumns:
    """Parse complete lines ``buf`` (ends with a newline) whose first line is ``first_line``."""
    check_control_bytes(buf, path, first_line)
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
        return empty_frames()
    bad(buf[starts] != 40, "not a candump -L line (expected '(<seconds>) <channel> <id>#<data>')")
    rpar = next_at(np.flatnonzero(buf == 41), starts)
    spaces = np.flatnonzero(buf == 32)
    sp1 = next_at(spaces, rpar)
    sp2 = next_at(spaces, sp1 + 1)
    bad((rpar >= ends) | (sp1 != rpar + 1) | (sp2 >= ends) | (sp2 == sp1 + 1),
        "not a candump -L line (expected '(<seconds>) <channel> <id>#<data>')")  # fmt: skip
    sp3 = next_at(spaces, sp2 + 1)
    frame_end = np.minimum(sp3, ends)
    # an optional direction token ' R' / ' T' after the frame
    has_dir = sp3 < ends
    dir_char = buf[np.minimum(sp3 + 1, len(buf) - 1)] | 32  # lower case
    bad(has_dir & ((ends != sp3 + 2) | ((dir_char != ord("r")) & (dir_char != ord("t")))),
        "unexpected text after the frame (expected ' R' or ' T')")  # fmt: skip
    is_rx = ~has_dir | (dir_char == ord("r"))
    hashes = np.flatnonzero(buf == 35)
    h = next_at(hashes, sp2 + 1)
    bad(h >= frame_end, "no '#' in the frame")

    # timestamp: the text between the parentheses, converted by the C library like float()
    tlen = rpar - starts - 1
    tw = int(tlen.max())
    ttext = gather(buf, starts + 1, tlen, tw)
    bad(bad_time_text(ttext, tlen), "bad timestamp (expected <digits>.<digits>)")
    t_s = timestamps(ttext, tlen)
    if t_s is None:  # more than 15 digits
        t_s = ttext.view(f"S{tw}").ravel().astype(np.float64)
    bad(~(t_s < T_MAX_S), T_PROBLEM)

    # id: hex digits between the second space and '#'
    idlen = h - sp2 - 1
    bad((idlen < 1) | (idlen > 8), "bad CAN id")
    idtext = gather(buf, sp2 + 1, idlen, 8)
    idval = HEX[idtext]
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
    fdflags = np.where(fd, HEX[buf[np.minimum(d0 + 1, len(buf) - 1)]], 0)
    bad(fd & ((d0 + 1 >= frame_end) | (fdflags == 255)), "bad CAN FD flags")
    dstart = np.where(fd, d0 + 2, d0)
    cs = buf[np.minimum(dstart, len(buf) - 1)] | 32
    remote = (dstart < frame_end) & (cs == ord("r"))
    dlen = np.maximum(frame_end - dstart, 0)
    rlen = np.where(remote, dlen - 1, 0)  # remote: optional decimal dlc
    rw = max(1, int(rlen.max()))
    rtext = DEC[gather(buf, dstart + 1, rlen, rw)]
    bad(remote & ((rtext == 255) & (np.arange(rw) < rlen[:, None])).any(axis=1), "bad remote dlc")
    rdlc = np.zeros(n, np.int64)
    for c in range(rw):
        rdlc = np.where(c < rlen, rdlc * 10 + rtext[:, c], rdlc)
    hexlen = np.where(remote, 0, dlen)
    bad((hexlen % 2 == 1) | (hexlen > 128), "bad data (expected up to 64 bytes as hex pairs)")
    bad(~fd & (hexlen > 16), "bad data (more than 8 bytes in a classic frame)")
    nbytes = hexlen // 2
    w = max(8, int(nbytes.max()))
    htext = HEX[gather(buf, dstart, hexlen, 2 * w)]
    bad(((htext == 255) & (np.arange(2 * w) < hexlen[:, None])).any(axis=1), "bad data (not hex)")
    htext[np.arange(2 * w) >= hexlen[:, None]] = 0
    data = (htext[:, 0::2] << 4) | htext[:, 1::2]
    dlc = np.where(remote, rdlc, nbytes)

    # channel: the text between the spaces (few distinct values); digits become an int
    clen = sp2 - sp1 - 1
    cw = int(clen.max())
    ctext = gather(buf, sp1 + 1, clen, cw).view(f"S{cw}").ravel()
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
