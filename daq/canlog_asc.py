"""Vector ASC logs (``.asc``) parsed with numpy into :class:`~cdpr.daq.can_frames.FrameColumns`,
equal field by field to python-can's ``ASCReader`` (see :func:`read_asc`)."""

from __future__ import annotations

import os
import re
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cdpr.analysis.errors import ConfigError

from .can_frames import (
    EXTENDED,
    ODD,
    RX,
    T_MAX_S,
    T_PROBLEM,
    FrameColumns,
    empty_frames,
    merge_by_line,
)
from .canlog_text import (
    CTRL,
    DEC,
    LineTokens,
    bad_time_text,
    check_control_bytes,
    check_utf8,
    gather,
    line_blocks,
    timestamps,
    tok_value,
)


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
        for text in line_blocks(fh, block_bytes, head.body_offset, progress):
            check_utf8(text, str(p), line)
            block = np.frombuffer(text, np.uint8)
            cols = _asc_block(block, str(p), line, head.base)
            line += int(np.count_nonzero(block == 10))
            if len(cols):
                yield cols


_DLC2LEN = np.array([0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64], np.int64)
_FD_LENGTHS = frozenset(_DLC2LEN.tolist())
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
            if CTRL[np.frombuffer(raw, np.uint8)].any() or len(text.splitlines()) > 1:
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


def _asc_block(buf: np.ndarray, path: str, first_line: int, base: int) -> FrameColumns:
    """Parse the complete body lines ``buf`` (ends with a newline) of an ASC file.

    Classic data frames (``<t> <ch> <id>[x] Rx|Tx d <dlc> <bytes> [Length = ...]``: the bulk of
    a log) are parsed with numpy from the positions of the whitespace-separated tokens; every
    other line (remote, error and CAN FD frames, events, comments) one at a time with the same
    rules as python-can's ``ASCReader``."""
    check_control_bytes(buf, path, first_line)
    lt = LineTokens.of(buf)
    if lt is None:  # blank lines only
        return empty_frames()
    nl, line_start, nlines = lt.nl, lt.line_start, lt.n_lines
    ntok, first_tok, tok_s, tok_len, tok = lt.ntok, lt.first_tok, lt.tok_s, lt.tok_len, lt.tok

    lines = np.arange(nlines)
    s4, l4 = tok(4, lines)
    s3, l3 = tok(3, lines)
    s1, l1 = tok(1, lines)
    c3 = gather(buf, s3, np.minimum(l3, 2), 2)
    cand = (
        (ntok >= 6)
        & (l4 == 1)
        & (buf[s4] == ord("d"))
        & (l3 == 2)
        & ((c3[:, 0] == ord("R")) | (c3[:, 0] == ord("T")))
        & (c3[:, 1] == ord("x"))
        & (l1 >= 1)
        & (DEC[buf[s1]] != 255)
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
    ttext = gather(buf, s0, l0, tw)
    bad(bad_time_text(ttext, l0), "bad timestamp (expected <digits>.<digits>)")
    t_s = timestamps(ttext, l0)
    if t_s is None:
        t_s = ttext.view(f"S{tw}").ravel().astype(np.float64)
    bad(~(t_s < T_MAX_S), T_PROBLEM)
    ch, ok = tok_value(buf, *tok(1, rows), 6, 10)
    bad(~ok, "bad channel")
    bad(non_ascii[rows], "not ASCII text in a frame line")
    s2, l2 = tok(2, rows)
    ext = (l2 >= 2) & ((buf[s2 + l2 - 1] | 32) == ord("x"))
    ids, ok = tok_value(buf, s2, l2 - ext, 8 if base == 16 else 10, base)
    bad(~ok, "bad CAN id")
    bad(ids > np.where(ext, 0x1FFFFFFF, 0x7FF), "CAN id out of range")
    dlc_raw, ok = tok_value(buf, *tok(5, rows), 2, base)
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
        v, ok = tok_value(buf, sk, lk, bw, base)
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
    return merge_by_line(fast, sc)


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
        v, ok = tok_value(buf, sk, lk, 2 if base == 16 else 3, base)
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
        fail(T_PROBLEM)
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
