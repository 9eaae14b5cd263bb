"""Vector BLF logs (``.blf``) read with numpy into :class:`~cdpr.daq.can_frames.FrameColumns`, equal
field by field to python-can's ``BLFReader`` (the layout below is python-can's, itself from Toby
Lorenz' ``vector_blf`` library; Vector publishes no specification).

A file is a 144-byte header (``LOGG``, the measurement's start as a SYSTEMTIME) and objects
(``LOBJ``, a 16-byte base header: header size, header version, object size, object type); the
top-level ones that matter are ``LOG_CONTAINER`` objects holding zlib-compressed (or stored)
inner objects, which may straddle containers.  Inner objects are 4-byte aligned; their header
(version 1: flags, client index, object version, timestamp; version 2 adds a timestamp status and
the original timestamp) gives the time in 10 us (flags 1) or 1 ns units from the start.  Read here,
as python-can reads them: ``CAN_MESSAGE`` and ``CAN_MESSAGE2`` (classic frames), ``CAN_FD_MESSAGE``,
``CAN_FD_MESSAGE_64`` and ``CAN_ERROR_EXT``; other objects (statistics, markers, ...) are skipped,
as python-can skips them.

The containers are decompressed one by one (zlib, in C) and their inner objects, ``block_bytes``
at a time, located with numpy: every ``LOBJ`` signature, chained through the object sizes (a
signature inside a payload is not on the chain); the fields of each object kind are then read as
columns.  A timestamp is ``ticks / 1e5`` or ``ticks / 1e9`` plus the start time: the same float
python-can computes through ``Decimal``.  Errors (a ConfigError naming the file and the byte):
a file that does not start with ``LOGG``, a top-level object without ``LOBJ``, an unknown
compression method (python-can warns and drops the container), a chain of inner objects that
breaks, and a file that ends inside an object (python-can stops silently).
"""

from __future__ import annotations

import datetime
import logging
import os
import struct
import zlib
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
    concat_frames,
    empty_frames,
)

log = logging.getLogger(__name__)

_FILE_HEADER = struct.Struct("<4sLBBBBBBBBQQLL8H8H")
_OBJ_BASE = struct.Struct("<4sHHLL")
_CONTAINER = struct.Struct("<H6xL4x")
LOG_CONTAINER = 10
CAN_MESSAGE, CAN_ERROR_EXT, CAN_MESSAGE2, CAN_FD_MESSAGE, CAN_FD_MESSAGE_64 = 1, 73, 86, 100, 101
_NO_COMPRESSION, _ZLIB = 0, 2
_CAN_MSG_EXT = 0x80000000
_DLC2LEN = np.array([0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64], np.int64)
_LOBJ = np.frombuffer(b"LOBJ", "<u4")[0]


def _start_time(st: tuple[int, ...]) -> float:
    """python-can's ``systemtime_to_timestamp`` (0 for an invalid SYSTEMTIME)."""
    try:
        return datetime.datetime(
            st[0], st[1], st[3], st[4], st[5], st[6], st[7] * 1000, tzinfo=datetime.UTC
        ).timestamp()
    except ValueError:
        return 0.0


def read_blf(
    path: str | os.PathLike[str],
    progress: Callable[[int], None] | None = None,
    block_bytes: int = 8 << 20,
) -> Iterator[FrameColumns]:
    """The frames of a Vector BLF log (see the module docstring), a block of decompressed objects
    at a time (``progress(bytes read)`` after each)."""
    p = Path(path)
    name = str(p)
    with p.open("rb") as fh:
        head = fh.read(_FILE_HEADER.size)
        if len(head) < _FILE_HEADER.size or head[:4] != b"LOGG":
            raise ConfigError(name, "byte 0", "not a BLF file (no LOGG signature)")
        header = _FILE_HEADER.unpack(head)
        start = _start_time(header[14:22])
        fh.read(header[1] - _FILE_HEADER.size)
        offset = header[1]
        pending = bytearray()
        pending_at = offset  # file offset of the container the pending bytes start in
        while True:
            base = fh.read(_OBJ_BASE.size)
            if not base:
                break
            if len(base) < _OBJ_BASE.size:
                raise ConfigError(name, f"byte {offset}", "the file ends inside an object header")
            sig, _, _, size, kind = _OBJ_BASE.unpack(base)
            if sig != b"LOBJ":
                raise ConfigError(name, f"byte {offset}", "not a BLF object (no LOBJ signature)")
            body = fh.read(size - _OBJ_BASE.size)
            if len(body) < size - _OBJ_BASE.size:
                raise ConfigError(name, f"byte {offset}", "the file ends inside an object")
            fh.read(size % 4)  # padding
            at, offset = offset, offset + size + size % 4
            if kind != LOG_CONTAINER:
                continue
            method, _ = _CONTAINER.unpack_from(body)
            data = body[_CONTAINER.size :]
            if method == _ZLIB:
                try:
                    data = zlib.decompress(data)
                except zlib.error as exc:
                    raise ConfigError(name, f"byte {at}", f"bad zlib data: {exc}") from None
            elif method != _NO_COMPRESSION:
                raise ConfigError(name, f"byte {at}", f"unknown compression method {method}")
            if not pending:
                pending_at = at
            pending += data
            if len(pending) >= block_bytes:
                cols, used = _parse(bytes(pending), start, name, pending_at)
                del pending[:used]
                pending_at = at
                if progress is not None:
                    progress(offset)
                if len(cols):
                    yield cols
        cols, used = _parse(bytes(pending), start, name, pending_at)
        if len(pending) - used >= 8:  # python-can ignores a cut object at the end; so not here
            raise ConfigError(
                name, f"byte {pending_at}", "the file ends inside an object (cut off?)"
            )
        if progress is not None:
            progress(offset)
        if len(cols):
            yield cols


def _objects(b: np.ndarray, name: str, at: int) -> tuple[np.ndarray, int]:
    """The positions of the complete inner objects of ``b`` (python-can's walk: from 0, the next
    object's ``LOBJ`` within 4 bytes after the end of the previous one) and where the first
    incomplete one starts (``len(b)`` when none is)."""
    n = len(b)
    if n < 16:
        return np.zeros(0, np.int64), 0
    word = np.ndarray((n - 3,), "<u4", b, 0, (1,))  # the 4 bytes at every offset
    cand = np.flatnonzero(word == _LOBJ)
    cand = cand[cand + 16 <= n]
    if not len(cand) or cand[0] > 4:
        raise ConfigError(name, f"byte {at}", "no BLF object where one should start")
    size = np.ndarray((n - 11,), "<u4", b, 8, (1,))[cand].astype(np.int64)
    end = cand + size
    # the chain: each object's successor is the first signature at or after its end (4-byte
    # alignment: at most 4 bytes later); signatures inside payloads fall off the chain
    nxt = np.searchsorted(cand, end)
    ok = np.ones(len(cand), bool)
    ok[nxt < len(cand)] = (
        cand[np.minimum(nxt, len(cand) - 1)][nxt < len(cand)] - end[nxt < len(cand)] <= 4
    )
    if bool((nxt[:-1] == np.arange(1, len(cand))).all()) and bool(ok[:-1].all()):
        chain = np.arange(len(cand))  # every signature is an object (the usual case)
    else:
        chain_l = []
        i = 0
        while i < len(cand):
            chain_l.append(i)
            if nxt[i] >= len(cand):
                break
            if not ok[i]:
                raise ConfigError(
                    name, f"byte {at}", f"BLF objects do not chain (at offset {int(end[i])})"
                )
            i = int(nxt[i])
        chain = np.array(chain_l, np.int64)
    pos = cand[chain]
    complete = end[chain] <= n
    if not complete.all():
        k = int(np.argmin(complete))
        return pos[:k], int(pos[k])
    return pos, int(end[chain][-1])  # what follows (padding, a cut object) waits for more


def _u(b: np.ndarray, at: np.ndarray, dtype: str) -> np.ndarray:
    """Little-endian integers of ``dtype`` at the byte offsets ``at``."""
    size = np.dtype(dtype).itemsize
    return b[at[:, None] + np.arange(size)].copy().view(dtype).ravel().astype(np.int64)


def _parse(buf: bytes, start: float, name: str, at: int) -> tuple[FrameColumns, int]:
    """The frames of the complete inner objects at the start of ``buf``, and the bytes used."""
    b = np.frombuffer(buf, np.uint8)
    pos, used = _objects(b, name, at)
    if not len(pos):
        return empty_frames(), used
    hsize = _u(b, pos + 4, "<u2")
    hver = _u(b, pos + 6, "<u2")
    osize = _u(b, pos + 8, "<u4")
    kind = _u(b, pos + 12, "<u4")
    known = np.isin(kind, (CAN_MESSAGE, CAN_MESSAGE2, CAN_ERROR_EXT, CAN_FD_MESSAGE,
                           CAN_FD_MESSAGE_64))  # fmt: skip
    bad_ver = known & ~np.isin(hver, (1, 2))
    if bad_ver.any():
        log.warning("%s: %d object(s) of unknown header version skipped (as python-can does)",
                    name, int(bad_ver.sum()))  # fmt: skip
    keep = known & ~bad_ver
    pos, hsize, hver, osize, kind = pos[keep], hsize[keep], hver[keep], osize[keep], kind[keep]
    if not len(pos):
        return empty_frames(), used
    flags = _u(b, pos + 16, "<u4")
    ticks = np.ndarray((len(b) - 7,), "<u8", b, 0, (1,))[pos + 24]
    t_s = _times(ticks, flags, start)
    late = np.flatnonzero(~(t_s < T_MAX_S))
    if len(late):
        raise ConfigError(name, f"byte {at + int(pos[late[0]])}", T_PROBLEM)
    body = pos + np.where(hver == 1, 32, 40)
    parts = []
    for kinds, reader in (
        ((CAN_MESSAGE, CAN_MESSAGE2), _can_message),
        ((CAN_ERROR_EXT,), _error_ext),
        ((CAN_FD_MESSAGE,), _fd_message),
        ((CAN_FD_MESSAGE_64,), _fd_message_64),
    ):
        sel = np.flatnonzero(np.isin(kind, kinds))
        if len(sel):
            cols = reader(b, body[sel], osize[sel], hsize[sel], t_s[sel])
            cols.line = sel.astype(np.int64)  # the object order, to merge the kinds back
            parts.append(cols)
    out = concat_frames(parts)
    if len(parts) > 1:
        out = out.take(np.argsort(out.line, kind="stable"))
    out.line = np.zeros(len(out), np.int64)
    return out, used


def _times(ticks: np.ndarray, flags: np.ndarray, start: float) -> np.ndarray:
    """python-can's ``float(Decimal(ticks) * factor) + start``: for ticks below 2**53 the IEEE
    quotient ``ticks / 10**k`` is that correctly rounded value; larger ones go through Decimal."""
    div = np.where(flags == 1, 1e5, 1e9)
    t = ticks.astype(np.float64) / div
    big = np.flatnonzero(ticks >= np.uint64(1 << 53))
    if len(big):
        from decimal import Decimal

        for i in big.tolist():
            f = Decimal("1e-5") if flags[i] == 1 else Decimal("1e-9")
            t[i] = float(Decimal(int(ticks[i])) * f)
    return t + start


def _columns(
    t_s: np.ndarray, ids_raw: np.ndarray, flags: np.ndarray, dlc: np.ndarray, data: np.ndarray,
    length: np.ndarray, channel: np.ndarray,
) -> FrameColumns:  # fmt: skip
    n = len(t_s)
    ch = np.empty(n, object)
    ch[:] = (channel - 1).tolist()
    flags = flags | EXTENDED * ((ids_raw & _CAN_MSG_EXT) != 0)
    length = np.where(flags & REMOTE, 0, length)  # python-can: a remote frame has no data
    data = np.where(np.arange(data.shape[1]) < length[:, None], data, 0).astype(np.uint8)
    return FrameColumns(
        t_s, ids_raw & 0x1FFFFFFF, flags.astype(np.uint8), dlc, data, length, ch,
        np.zeros(n, np.int64),
    )  # fmt: skip


def _bytes(b: np.ndarray, at: np.ndarray, width: int) -> np.ndarray:
    idx = np.minimum(at[:, None] + np.arange(width), len(b) - 1)
    return b[idx]


def _can_message(
    b: np.ndarray, at: np.ndarray, osize: np.ndarray, hsize: np.ndarray, t_s: np.ndarray
) -> FrameColumns:
    """``CAN_MESSAGE``/``CAN_MESSAGE2``: channel u16, flags u8 (0x01 transmitted, 0x80 remote),
    dlc u8, id u32 (bit 31 extended), 8 data bytes; data: the first min(dlc, 8)."""
    fl = b[at + 2].astype(np.int64)
    dlc = b[at + 3].astype(np.int64)
    flags = REMOTE * ((fl & 0x80) != 0) | RX * ((fl & 0x01) == 0)
    return _columns(t_s, _u(b, at + 4, "<u4"), flags, dlc, _bytes(b, at + 8, 8),
                    np.minimum(dlc, 8), _u(b, at, "<u2"))  # fmt: skip


def _error_ext(
    b: np.ndarray, at: np.ndarray, osize: np.ndarray, hsize: np.ndarray, t_s: np.ndarray
) -> FrameColumns:
    """``CAN_ERROR_EXT``: channel u16, length u16, flags u32, ecc, position, dlc u8, frame length
    u32, id u32, flags ext u16, 8 data bytes; an error frame, received, data min(dlc, 8)."""
    dlc = b[at + 10].astype(np.int64)
    flags = np.full(len(at), ERROR | RX, np.int64)
    return _columns(t_s, _u(b, at + 16, "<u4"), flags, dlc, _bytes(b, at + 24, 8),
                    np.minimum(dlc, 8), _u(b, at, "<u2"))  # fmt: skip


def _fd_message(
    b: np.ndarray, at: np.ndarray, osize: np.ndarray, hsize: np.ndarray, t_s: np.ndarray
) -> FrameColumns:
    """``CAN_FD_MESSAGE``: channel u16, flags u8, dlc u8 (a DLC code), id u32, frame length u32,
    bit count u8, FD flags u8 (1 EDL, 2 BRS, 4 ESI), valid bytes u8, 5 spare, 64 data bytes."""
    fl = b[at + 2].astype(np.int64)
    fd = b[at + 13].astype(np.int64)
    dlc = _dlc2len(b[at + 3].astype(np.int64))
    flags = (REMOTE * ((fl & 0x80) != 0) | RX * ((fl & 0x01) == 0) | FD * ((fd & 1) != 0)
             | BRS * ((fd & 2) != 0) | ESI * ((fd & 4) != 0))  # fmt: skip
    valid = np.minimum(b[at + 14].astype(np.int64), 64)
    return _columns(t_s, _u(b, at + 4, "<u4"), flags, dlc, _bytes(b, at + 20, 64), valid,
                    _u(b, at, "<u2"))  # fmt: skip


def _fd_message_64(
    b: np.ndarray, at: np.ndarray, osize: np.ndarray, hsize: np.ndarray, t_s: np.ndarray
) -> FrameColumns:
    """``CAN_FD_MESSAGE_64``: channel u8, dlc u8, valid bytes u8, tx count u8, id u32, frame length
    u32, flags u32 (0x10 remote, 0x1000 EDL, 0x2000 BRS, 0x4000 ESI), 4 more u32, bit count u16,
    direction u8, ext data offset u8, crc u32, then the data: as many bytes as fit before the
    extension (python-can issue 1905: zero-padded up to the valid bytes)."""
    fd = _u(b, at + 12, "<u4")
    dlc = _dlc2len(b[at + 1].astype(np.int64))
    valid = b[at + 2].astype(np.int64)
    ext_off = b[at + 35].astype(np.int64)
    room = np.where(ext_off != 0, ext_off, osize) - hsize - 40
    have = np.clip(np.minimum(valid, room), 0, None)
    flags = (REMOTE * ((fd & 0x10) != 0) | RX * (b[at + 34] == 0) | FD * ((fd & 0x1000) != 0)
             | BRS * ((fd & 0x2000) != 0) | ESI * ((fd & 0x4000) != 0))  # fmt: skip
    w = max(8, int(valid.max()))
    data = _bytes(b, at + 40, w)
    data = np.where(np.arange(w) < have[:, None], data, 0)
    return _columns(t_s, _u(b, at + 4, "<u4"), flags, dlc, data, valid,
                    b[at].astype(np.int64))  # fmt: skip


def _dlc2len(dlc: np.ndarray) -> np.ndarray:
    return np.where(dlc > 15, 64, _DLC2LEN[np.minimum(dlc, 15)])
