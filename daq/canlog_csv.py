"""python-can's CSV logs (``.csv``, written by its ``CSVWriter``) parsed with numpy into
:class:`~cdpr.daq.can_frames.FrameColumns`, equal field by field to python-can's ``CSVReader``.

The first line is a header (skipped, as python-can skips it); every other line is
``timestamp,arbitration_id,extended,remote,error,dlc,data``: the timestamp as Python's ``repr`` of
the float (read back by the same conversion as ``float()``), the id in hex (``0x181``), the three
flags ``1`` or anything else, the DLC in decimal and the data in base64.  No channel, received,
never CAN FD (the layout has no field for them).  A line of another number of fields (python-can
raises), a bad number or bad base64 is a ConfigError naming the file and the line; blank lines are
skipped.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from cdpr.analysis.errors import ConfigError

from .can_frames import ERROR, EXTENDED, REMOTE, RX, T_MAX_S, T_PROBLEM, FrameColumns, empty_frames
from .canlog_text import (
    bad_time_text,
    check_control_bytes,
    check_utf8,
    gather,
    line_blocks,
    timestamps,
    tok_value,
)

_B64 = np.full(256, 255, np.uint8)
for _i, _c in enumerate(b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/"):
    _B64[_c] = _i
_FLOAT_CHARS = np.zeros(256, bool)
_FLOAT_CHARS[list(b"0123456789.eE+-")] = True


def read_csv(
    path: str | os.PathLike[str],
    progress: Callable[[int], None] | None = None,
    block_bytes: int = 8 << 20,
) -> Iterator[FrameColumns]:
    """The frames of a python-can CSV log (see the module docstring), ``block_bytes`` of text at
    a time."""
    p = Path(path)
    with p.open("rb") as fh:
        header = fh.readline()
        line = 2
        for text in line_blocks(fh, block_bytes, len(header), progress):
            check_utf8(text, str(p), line)
            block = np.frombuffer(text, np.uint8)
            cols = _block(block, str(p), line)
            line += int(np.count_nonzero(block == 10))
            if len(cols):
                yield cols


def _block(buf: np.ndarray, path: str, first_line: int) -> FrameColumns:
    check_control_bytes(buf, path, first_line)
    nl = np.flatnonzero(buf == 10).astype(np.int64)
    start = np.concatenate([[0], nl[:-1] + 1])
    end = nl - (buf[np.maximum(nl - 1, 0)] == 13)  # a CRLF line ends before its CR
    rows = np.flatnonzero(end > start)  # blank lines skipped
    start, end = start[rows], end[rows]
    n = len(rows)
    if n == 0:
        return empty_frames()
    commas = np.flatnonzero(buf == 44).astype(np.int64)
    first = np.searchsorted(commas, start)
    count = np.searchsorted(commas, end) - first

    def bad(mask: np.ndarray, problem: str) -> None:
        if mask.any():
            i = int(np.flatnonzero(mask)[0])
            text = bytes(buf[start[i] : end[i]]).decode("utf-8", "replace")
            raise ConfigError(
                path, f"line {first_line + int(rows[i])}", f"{problem}: {text[:80]!r}"
            )

    bad(count != 6, "expected 7 comma-separated fields (timestamp, arbitration_id, extended, "
                    "remote, error, dlc, data)")  # fmt: skip
    cut = commas[first[:, None] + np.arange(6)]  # (n, 6)
    f_start = np.concatenate([start[:, None], cut + 1], axis=1)
    f_end = np.concatenate([cut, end[:, None]], axis=1)
    f_len = f_end - f_start

    # timestamp: float() of the text
    tl = f_len[:, 0]
    tw = max(1, int(tl.max()))
    ttext = gather(buf, f_start[:, 0], tl, tw)
    inside = np.arange(tw) < tl[:, None]
    bad((tl == 0) | (inside & ~_FLOAT_CHARS[ttext]).any(axis=1), "bad timestamp")
    # <digits>.<digits> of at most 15 digits (the usual repr): exactly as float(), with numpy;
    # any other float text through numpy's conversion, which is float()'s too
    t_s = None if bad_time_text(ttext, tl).any() else timestamps(ttext, tl)
    try:
        if t_s is None:
            t_s = ttext.view(f"S{tw}").ravel().astype(np.float64)
    except ValueError:
        t_s = np.array([_float(x) for x in ttext.view(f"S{tw}").ravel().tolist()])
        bad(np.isnan(t_s) & (ttext[:, 0] != ord("n")), "bad timestamp")
    bad(~(t_s < T_MAX_S), T_PROBLEM)
    # id: hex, with python's optional 0x
    s1, l1 = f_start[:, 1], f_len[:, 1]
    x = (
        (l1 > 2)
        & (buf[s1] == ord("0"))
        & ((buf[np.minimum(s1 + 1, len(buf) - 1)] | 32) == ord("x"))
    )
    ids, ok = tok_value(buf, s1 + 2 * x, l1 - 2 * x, 8, 16)
    bad(~ok, "bad arbitration id")

    def is_one(k: int) -> np.ndarray:
        return (f_len[:, k] == 1) & (buf[f_start[:, k]] == ord("1"))

    ext, remote, error = is_one(2), is_one(3), is_one(4)
    dlc, ok = tok_value(buf, f_start[:, 5], f_len[:, 5], 3, 10)
    bad(~ok, "bad DLC")
    data, length = _base64(buf, f_start[:, 6], f_len[:, 6], bad)
    length = np.where(remote, 0, length)  # python-can: a remote frame has no data
    data[remote] = 0
    flags = EXTENDED * ext | REMOTE * remote | ERROR * error | RX
    ch = np.empty(n, object)
    return FrameColumns(
        t_s, ids, flags.astype(np.uint8), dlc, data, length.astype(np.int64), ch,
        first_line + rows,
    )  # fmt: skip


def _float(text: bytes) -> float:
    try:
        return float(text)
    except ValueError:
        return float("nan")


def _base64(buf, start, length, bad):  # noqa: ANN001, ANN202
    """The bytes of base64 fields (groups of 4 characters, ``=`` padding at the end)."""
    n = len(start)
    bad(length % 4 != 0, "bad data (base64 of a length not a multiple of 4)")
    w = int(length.max()) if n else 0
    data = np.zeros((n, max(8, 3 * w // 4)), np.uint8)
    if not w:
        return data, np.zeros(n, np.int64)
    text = gather(buf, start, length, w)
    inside = np.arange(w) < length[:, None]
    pad = (text == ord("=")) & inside
    npad = pad.sum(axis=1)
    tail_ok = ~pad | (np.arange(w) >= length[:, None] - npad[:, None])  # '=' only at the end
    val = _B64[text]
    bad((npad > 2) | ~tail_ok.all(axis=1) | (inside & ~pad & (val == 255)).any(axis=1),
        "bad data (not base64)")  # fmt: skip
    v = np.where(inside & ~pad, val, 0).astype(np.uint32).reshape(n, -1, 4)
    word = v[:, :, 0] << 18 | v[:, :, 1] << 12 | v[:, :, 2] << 6 | v[:, :, 3]
    b3 = np.stack([word >> 16, (word >> 8) & 0xFF, word & 0xFF], axis=2).reshape(n, -1)
    nbytes = 3 * (length // 4) - npad
    data[:, : b3.shape[1]] = np.where(np.arange(b3.shape[1]) < nbytes[:, None], b3, 0)
    return data, nbytes
