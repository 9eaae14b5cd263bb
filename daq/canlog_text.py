"""Helpers of the numpy text parsers of CAN logs (:mod:`cdpr.daq.canlog_candump`,
:mod:`cdpr.daq.canlog_asc`, :mod:`cdpr.daq.canlog_trc`, :mod:`cdpr.daq.canlog_csv`): digit tables,
fields gathered from a block of lines, timestamps converted exactly as ``float()`` converts them,
blocks of whole lines read from a file, and the checks every text format shares (control bytes,
UTF-8)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from cdpr.analysis.errors import ConfigError

HEX = np.full(256, 255, np.uint8)
for _i, _c in enumerate(b"0123456789abcdef"):
    HEX[_c] = _i
for _i, _c in enumerate(b"ABCDEF"):
    HEX[_c] = 10 + _i
#: control bytes no CAN log line holds (tab, carriage return and newline aside)
CTRL = np.zeros(256, bool)
CTRL[[*range(9), *range(11, 13), *range(14, 32), 127]] = True
DEC = np.full(256, 255, np.uint8)
for _i, _c in enumerate(b"0123456789"):
    DEC[_c] = _i


def next_at(positions: np.ndarray, after: np.ndarray) -> np.ndarray:
    """For each value of ``after``, the first of the sorted ``positions`` >= it (or a huge
    number)."""
    ext = np.append(positions, np.iinfo(np.int64).max // 2)
    return ext[np.searchsorted(positions, after)]


def gather(buf: np.ndarray, start: np.ndarray, length: np.ndarray, width: int) -> np.ndarray:
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
    elif n and len(buf) >= width:
        # any starts: rows of the buffer's sliding windows (a row copied at a time); the few
        # that would run past its end byte by byte
        win = np.lib.stride_tricks.sliding_window_view(buf, width)
        inside = start <= len(buf) - width
        if bool(inside.all()):
            out = win[start]
        else:
            out = np.empty((n, width), np.uint8)
            out[inside] = win[start[inside]]
            idx = start[~inside, None] + np.arange(width)
            out[~inside] = buf[np.minimum(idx, len(buf) - 1)]
    else:
        idx = start[:, None] + np.arange(width)
        out = buf[np.minimum(idx, max(len(buf) - 1, 0))]
    if not bool(np.all(length == width)):
        out[np.arange(width) >= length[:, None]] = 0
    return out


_PAIR = np.arange(1 << 16)
_PAIR_1ST, _PAIR_2ND = _PAIR & 0xFF, _PAIR >> 8  # two bytes read as a little-endian uint16
#: the value of two hex digits (0-255), 256 for anything else
HEX2 = np.where(
    (HEX[_PAIR_1ST] < 16) & (HEX[_PAIR_2ND] < 16),
    HEX[_PAIR_1ST].astype(np.uint16) * 16 + HEX[_PAIR_2ND],
    256,
).astype(np.uint16)
#: the value of two decimal digits (0-99), 256 for anything else
DEC2 = np.where(
    (DEC[_PAIR_1ST] < 10) & (DEC[_PAIR_2ND] < 10),
    DEC[_PAIR_1ST].astype(np.uint16) * 10 + DEC[_PAIR_2ND],
    256,
).astype(np.uint16)


def pairs(rows: np.ndarray, start: int, stop: int, table: np.ndarray) -> np.ndarray:
    """``table`` of the byte pairs of columns ``start:stop`` of ``rows``: (n, ceil(width / 2));
    an odd width gets a leading '0'."""
    n, w = len(rows), stop - start
    c = np.empty((n, w + w % 2), np.uint8)
    c[:, : w % 2] = 48
    c[:, w % 2 :] = rows[:, start:stop]
    return table.take(c.view("<u2"))


def fixed_timestamps(ipairs: np.ndarray, fpairs: np.ndarray, ni: int, k: int) -> np.ndarray | None:
    """float64 of timestamps of ``ni`` integer and ``k`` fraction digits, given as two-digit
    values (0-99, a leading '0' for an odd count), exactly as ``float()`` converts the text, or
    None (more than 15 digits on a side; more than 15 in all with an integer part of 0 or of 2**40
    or more).

    The integer part I and the fraction F are matrix products: every product and partial sum is
    an integer below 2**53, exact in float64 in any summation order.  Up to 15 digits in all:
    N = I * 10**k + F is below 2**53 and N / 10**k (both exact) rounds as ``float()``, as in
    :func:`timestamps`.  More digits: the value is rounded to 53 bits in integer arithmetic:
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


def check_control_bytes(buf: np.ndarray, path: str, first_line: int) -> None:
    """A ConfigError naming the first line of ``buf`` that holds a control byte (a carriage return
    is one unless a newline follows it)."""
    ctrl = CTRL[buf]
    cr = buf == 13
    lone = cr[:-1] & (buf[1:] != 10)  # a carriage return only before a newline
    if not (ctrl.any() or lone.any() or (len(buf) and cr[-1])):
        return
    at = np.union1d(np.flatnonzero(ctrl), np.flatnonzero(np.append(lone, cr[-1:])))
    if len(at):
        line = first_line + int(np.count_nonzero(buf[: at[0]] == 10))
        raise ConfigError(path, f"line {line}", f"control byte 0x{int(buf[at[0]]):02x} in the line")


def bad_time_text(ttext: np.ndarray, tlen: np.ndarray) -> np.ndarray:
    """Rows of (n, w) texts that are not ``<digits>.<digits>`` (the form candump and Vector
    write; ``float()`` would also take exponents, signs, ``inf``...)."""
    inside = np.arange(ttext.shape[1]) < tlen[:, None]
    isdot = (ttext == 46) & inside
    ndig = np.count_nonzero((DEC[ttext] != 255) & inside, axis=1)
    dot_at = np.argmax(isdot, axis=1)
    return (isdot.sum(axis=1) != 1) | (ndig != tlen - 1) | (dot_at == 0) | (dot_at == tlen - 1)


def timestamps(ttext: np.ndarray, tlen: np.ndarray) -> np.ndarray | None:
    """float64 of decimal texts ``<digits>.<digits>`` (n, w) exactly as ``float()`` gives them, or
    None when a text is not of that form.  The digits make an integer N < 2**53 and the value is
    N / 10**k for k fraction digits: both exact in float64, so IEEE division rounds the quotient
    correctly, which is what ``float()`` does with the text."""
    n, w = ttext.shape
    inside = np.arange(w) < tlen[:, None]
    digit = DEC[ttext]
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


def line_blocks(
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


def check_utf8(text: bytes, path: str, first_line: int) -> None:
    """python-can reads an ASC file as text: a byte sequence that is not UTF-8 is an error."""
    try:
        text.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = first_line + text.count(b"\n", 0, exc.start)
        raise ConfigError(path, f"line {line}", "not UTF-8 text") from None


#: token separators of a line: tab, carriage return, space (other control bytes are errors)
WS = np.zeros(256, bool)
WS[[9, 13, 32]] = True
_SEP = WS.copy()
_SEP[10] = True  # and the newline


@dataclass
class LineTokens:
    """The whitespace-separated tokens of a block of complete lines ``buf`` (ends with a newline),
    located with numpy: line ``r`` spans ``line_start[r] .. nl[r]`` and has ``ntok[r]`` tokens,
    token ``first_tok[r] + k`` being its k-th (start ``tok_s``, length ``tok_len``)."""

    buf: np.ndarray
    nl: np.ndarray
    line_start: np.ndarray
    tok_s: np.ndarray
    tok_len: np.ndarray
    first_tok: np.ndarray
    ntok: np.ndarray

    @property
    def n_lines(self) -> int:
        return len(self.nl)

    @classmethod
    def of(cls, buf: np.ndarray) -> LineTokens | None:
        """The tokens of ``buf``, or None for a block of blank lines."""
        nl = np.flatnonzero(buf == 10).astype(np.int64)
        if len(nl) == 0:
            return None
        line_start = np.concatenate([[0], nl[:-1] + 1])
        sep = _SEP[buf]
        # the edges alternate, separator -> token (a start), token -> separator (an end)
        edge = np.flatnonzero(np.diff(sep.view(np.int8), prepend=np.int8(1), append=np.int8(1)))
        if len(edge) == 0:
            return None
        tok_s, tok_e = edge[0::2].astype(np.int64), edge[1::2].astype(np.int64)
        # tokens never cross a newline: a line's tokens run from its first to the next line's
        first_tok = np.searchsorted(tok_s, line_start)
        ntok = np.diff(first_tok, append=len(tok_s))
        return cls(buf, nl, line_start, tok_s, tok_e - tok_s, first_tok, ntok)

    def tok(self, k: int, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Start and length of token ``k`` of lines ``rows`` (length 0 when missing)."""
        have = self.ntok[rows] > k
        if bool(have.all()):
            i = self.first_tok[rows] + k
            return self.tok_s[i], self.tok_len[i]
        i = np.where(have, self.first_tok[rows] + k, 0)
        return np.where(have, self.tok_s[i], 0), np.where(have, self.tok_len[i], 0)

    def matrix(self, rows: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Start and length (n, k) of the first ``k`` tokens of lines ``rows`` (length 0 where a
        line has fewer): one gather for every field a parser reads."""
        have = self.ntok[rows, None] > np.arange(k)
        i = self.first_tok[rows, None] + np.arange(k)
        if not bool(have.all()):
            i = np.where(have, i, 0)
            return np.where(have, self.tok_s[i], 0), np.where(have, self.tok_len[i], 0)
        return self.tok_s[i], self.tok_len[i]

    def text(self, r: int) -> str:
        """Line ``r`` as text (stripped)."""
        return bytes(self.buf[self.line_start[r] : self.nl[r]]).decode("utf-8", "replace").strip()


def tok_value(
    buf: np.ndarray, start: np.ndarray, length: np.ndarray, width: int, base: int
) -> tuple[np.ndarray, np.ndarray]:
    """Integer values of tokens of up to ``width`` digits in ``base`` and whether each is one."""
    n = len(start)
    if n == 0:
        return np.zeros(0, np.int64), np.ones(0, bool)
    table = HEX if base == 16 else DEC
    dig = table[gather(buf, start, np.minimum(length, width), width)]
    inside = np.arange(width) < length[:, None]
    ok = (length >= 1) & (length <= width) & ~((dig == 255) & inside).any(axis=1)
    val = np.zeros(n, np.int64)
    for c in range(width):
        val = np.where(inside[:, c], val * base + dig[:, c], val)
    return val, ok
