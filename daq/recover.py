"""Salvage damaged or truncated MCAP run files: a record scanner that survives damage, and
:func:`recover_run`.

:func:`scan_mcap` walks the file's records itself (opcode, 8-byte length, body) instead of trusting
one streaming reader to the first error: a chunk that cannot be decompressed, fails its CRC or
does not parse is *skipped* and named (byte offset, log-time range, reason); framing that no
longer makes sense (a bad opcode, a length past the end of the file) is skipped by a *resync* on
the next well-formed chunk record (its length fields must agree exactly, and a valid record must
follow it).  A file that simply ends is *truncated*, not damaged.  A footer whose summary section
fails its CRC (or starts outside the file) is damage too (:func:`footer_check`, which
:func:`cdpr.daq.run_reader.open_run` uses as well).  Schemas and channels of a file whose footer and
summary survived are also read from its summary section, so messages of a channel whose first
chunk was lost can still be salvaged.  :func:`check_mcap` runs the same scan without expanding the
chunks (each is still decompressed and its CRC checked): what ``cdpr inspect`` reports as damage.
"""

from __future__ import annotations

import io
import mmap
import os
import struct
import time
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cdpr.analysis.errors import ConfigError, InputError

MAGIC = b"\x89MCAP0\r\n"
_CHUNK, _FOOTER, _DATA_END = 0x06, 0x02, 0x0F
_U64 = struct.Struct("<Q")
_U32 = struct.Struct("<I")
_CHUNK_FIXED = 8 + 8 + 8 + 4  # start, end, uncompressed size, crc (then the compression string)
_FOOTER_LEN = 1 + 8 + 8 + 8 + 4  # opcode, record length, summary start, summary offset start, crc


@dataclass
class Damage:
    """A part of the file that could not be read: byte ``offset``, ``length`` (bytes) and why."""

    offset: int
    length: int
    reason: str
    log_time_ns: tuple[int, int] | None = None

    def __str__(self) -> str:
        t = ""
        if self.log_time_ns is not None:
            t = f", log time {self.log_time_ns[0] / 1e9:.3f}..{self.log_time_ns[1] / 1e9:.3f} s"
        return f"{self.length} bytes at offset {self.offset}{t}: {self.reason}"


@dataclass
class Scan:
    """What :func:`scan_mcap` found besides the records it yielded."""

    size: int = 0
    complete: bool = False  # a footer, then the closing magic, at the end of the file
    chunks_ok: int = 0
    skipped: list[Damage] = field(default_factory=list)  # damage inside the file
    truncated_at: int | None = None  # the file ends inside a record (a crash, a cut)
    truncated_reason: str = ""
    orphans: int = 0  # messages whose channel is defined nowhere readable


def _decompress(compression: str, data: bytes, size: int) -> bytes:
    if compression == "":
        return data
    if compression == "zstd":
        import zstandard

        return zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
    if compression == "lz4":
        import lz4.frame

        return bytes(lz4.frame.decompress(data))
    raise ValueError(f"unknown compression {compression!r}")


def _chunk_at(buf: Any, i: int, size: int) -> bool:
    """True when a well-formed chunk record starts at ``i``: its length fields agree exactly and
    a valid opcode (or the end of the file) follows it."""
    if i + 9 + _CHUNK_FIXED + 4 > size or buf[i] != _CHUNK:
        return False
    (length,) = _U64.unpack_from(buf, i + 1)
    end = i + 9 + length
    if end > size or length < _CHUNK_FIXED + 4 + 8:
        return False
    (clen,) = _U32.unpack_from(buf, i + 9 + _CHUNK_FIXED)
    if clen > 4 or i + 9 + _CHUNK_FIXED + 4 + clen + 8 > end:
        return False
    comp = bytes(buf[i + 9 + _CHUNK_FIXED + 4 : i + 9 + _CHUNK_FIXED + 4 + clen])
    if comp not in (b"", b"zstd", b"lz4"):
        return False
    (rlen,) = _U64.unpack_from(buf, i + 9 + _CHUNK_FIXED + 4 + clen)
    if _CHUNK_FIXED + 4 + clen + 8 + rlen != length:
        return False
    return end == size or (end < size and 0x01 <= buf[end] <= 0x0F)


def _resync(buf: Any, start: int, size: int) -> int | None:
    """The offset of the next well-formed chunk record at or after ``start`` (None: none)."""
    i = start
    while True:
        i = buf.find(b"\x06", i, size)
        if i < 0:
            return None
        if _chunk_at(buf, i, size):
            return i
        i += 1


def _records(data: bytes, parse: dict[int, Any]) -> Iterator[Any]:
    """The records of a chunk's uncompressed body (raises on a malformed one)."""
    pos, n = 0, len(data)
    while pos < n:
        if pos + 9 > n:
            raise ValueError(f"record header cut at {pos} of {n} bytes")
        op = data[pos]
        (length,) = _U64.unpack_from(data, pos + 1)
        if pos + 9 + length > n:
            raise ValueError(f"record of {length} bytes at {pos} past the end ({n} bytes)")
        cls = parse.get(op)
        if cls is not None:
            yield _read(cls, data[pos + 9 : pos + 9 + length])
        pos += 9 + length


def _read(cls: Any, body: bytes) -> Any:
    """One record from its body (a Message's reader needs the body's length)."""
    from mcap.data_stream import ReadDataStream
    from mcap.records import Message

    stream = ReadDataStream(io.BytesIO(body))
    rec = cls.read(stream, len(body)) if cls is Message else cls.read(stream)
    if stream.count != len(body) and cls is not Message:
        raise ValueError(f"{cls.__name__} record: {stream.count} of {len(body)} bytes parsed")
    return rec


def _parsers() -> dict[int, Any]:
    from mcap.records import Attachment, Channel, Chunk, Footer, Message, Metadata, Schema

    return {
        0x02: Footer,
        0x03: Schema,
        0x04: Channel,
        0x05: Message,
        0x06: Chunk,
        0x09: Attachment,
        0x0C: Metadata,
    }


def footer_check(buf: Any, size: int) -> tuple[int | None, str]:
    """The end of an MCAP file (``buf``: its bytes, ``size`` long): the summary section's start
    offset (None: no summary section) and what is wrong ("" when nothing): the closing magic, the
    footer record before it, a summary start inside the file, the summary CRC (spec: every byte
    from the summary start through the footer's ``summary_offset_start``; 0 = not given)."""
    if size < 8 + _FOOTER_LEN + 8:
        return None, "the file is too short for a footer"
    if bytes(buf[size - 8 : size]) != MAGIC:
        return None, "no closing magic bytes (no footer)"
    f = size - 8 - _FOOTER_LEN
    if buf[f] != _FOOTER or _U64.unpack_from(buf, f + 1)[0] != _FOOTER_LEN - 9:
        return None, f"no footer record at offset {f}"
    (start,) = _U64.unpack_from(buf, f + 9)
    (offsets,) = _U64.unpack_from(buf, f + 17)
    (crc,) = _U32.unpack_from(buf, f + 25)
    if start == 0:
        return None, ""
    if not 8 <= start <= f or not (offsets == 0 or start <= offsets <= f):
        return None, f"the footer's summary offsets ({start}, {offsets}) lie outside the file"
    if crc and zlib.crc32(buf[start : f + 25]) != crc:
        return None, f"the summary section at offset {start} fails its CRC"
    return start, ""


def _summary_definitions(buf: Any, size: int, parse: dict[int, Any]) -> list[Any]:
    """Schemas and channels of the summary section of a file whose footer and summary CRC
    survived ([] if not)."""
    from mcap.records import Channel, Schema

    start, _ = footer_check(buf, size)
    if start is None:
        return []
    try:
        recs = list(_records(bytes(buf[start : size - 8 - _FOOTER_LEN]), parse))
    except Exception:  # a summary that does not parse: the data section is all there is
        return []
    return [r for r in recs if isinstance(r, Schema | Channel)]


def scan_mcap(path: str | os.PathLike[str], scan: Scan, expand: bool = True) -> Iterator[Any]:
    """Every readable Schema, Channel, Message, Metadata and Attachment record of an MCAP file, in
    file order (chunks expanded), filling ``scan`` with what was skipped or cut.  ``expand=False``:
    a chunk is decompressed and its CRC checked (its records' framing too when it has no CRC), but
    its records are not parsed nor yielded.

    Raises :class:`ConfigError` for a file that is missing, empty or not MCAP.
    """
    from mcap.records import Chunk, Footer

    p = Path(path)
    if not p.is_file():
        raise ConfigError(str(p), "", "file not found")
    parse = _parsers()
    chunk_parse = {k: v for k, v in parse.items() if k in (0x03, 0x04, 0x05)}
    with p.open("rb") as fh:
        size = os.fstat(fh.fileno()).st_size
        scan.size = size
        if size < 8 or fh.read(8) != MAGIC:
            raise ConfigError(str(p), "", "not an MCAP file (bad or missing magic bytes)")
        if size == 8:
            scan.truncated_at, scan.truncated_reason = 8, "the file ends after its magic bytes"
            return
        buf = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)
        try:
            yield from _summary_definitions(buf, size, parse)
            pos = 8
            while pos < size:
                if pos + 9 > size:
                    scan.truncated_at = pos
                    scan.truncated_reason = f"record header cut short at offset {pos}"
                    break
                op = buf[pos]
                (length,) = _U64.unpack_from(buf, pos + 1)
                bad = ""
                if not 0x01 <= op <= 0x0F:
                    bad = f"invalid record opcode 0x{op:02X}"
                elif pos + 9 + length > size:
                    nxt = _resync(buf, pos + 1, size)
                    if nxt is None:  # nothing readable after it: the file was cut here
                        scan.truncated_at = pos
                        scan.truncated_reason = (
                            f"record at offset {pos} needs {length} bytes, "
                            f"{size - pos - 9} left (file cut short)"
                        )
                        break
                    bad = f"record length {length} runs past the end of the file"
                if bad:
                    nxt = _resync(buf, pos + 1, size)
                    end = size if nxt is None else nxt
                    scan.skipped.append(Damage(pos, end - pos, bad + "; resynchronised"))
                    if nxt is None:
                        break
                    pos = nxt
                    continue
                body_end = pos + 9 + length
                cls = parse.get(op)
                if op == _CHUNK:
                    rec = None
                    try:
                        rec = _read(Chunk, buf[pos + 9 : body_end])
                        data = _decompress(rec.compression, rec.data, rec.uncompressed_size)
                        if rec.uncompressed_crc and zlib.crc32(data) != rec.uncompressed_crc:
                            raise ValueError("CRC mismatch of the uncompressed chunk")
                        if expand or not rec.uncompressed_crc:
                            inner = list(_records(data, chunk_parse if expand else {}))
                        else:
                            inner = []
                    except Exception as exc:
                        span = (
                            (rec.message_start_time, rec.message_end_time)
                            if rec is not None
                            else None
                        )
                        why = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
                        scan.skipped.append(Damage(pos, 9 + length, f"chunk skipped ({why})", span))
                    else:
                        scan.chunks_ok += 1
                        if expand:
                            yield from inner
                elif cls is not None:
                    try:
                        rec = _read(cls, buf[pos + 9 : body_end])
                    except Exception as exc:
                        why = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
                        scan.skipped.append(Damage(pos, 9 + length, f"record skipped ({why})"))
                    else:
                        if isinstance(rec, Footer):
                            scan.complete = body_end == size - 8 and (
                                bytes(buf[size - 8 : size]) == MAGIC
                            )
                            _, why = footer_check(buf, size)
                            if scan.complete and why:
                                start = rec.summary_start if 8 <= rec.summary_start < pos else pos
                                scan.skipped.append(Damage(start, size - start, why))
                            break
                        yield rec
                pos = body_end
        finally:
            buf.close()


def check_mcap(path: str | os.PathLike[str]) -> Scan:
    """What is damaged or cut in an MCAP file: :func:`scan_mcap` without expanding the chunks
    (every chunk still decompressed and CRC-checked)."""
    scan = Scan()
    for _ in scan_mcap(path, scan, expand=False):
        pass
    return scan


def recover_run(
    path: str | os.PathLike[str], out_path: str | os.PathLike[str] | None = None
) -> tuple[Path, Any]:
    """Salvage a truncated or damaged run file into ``<run>.recovered.mcap``.

    Every readable chunk, before and after any damage, and every schema, channel, metadata record
    and attachment is copied into a new, finished file; damaged chunks are skipped and named in
    the ``recovery`` metadata record (``skipped``, one line per part) and in ``contents.error``.
    The original is left untouched; an existing output is never overwritten.  Raises
    :class:`InputError` (and writes nothing) when nothing could be salvaged.  Returns the new path
    and a :class:`~cdpr.daq.mcap_io.RunContents` (messages as ``(log_time_ns, {})``).
    """
    import json

    from mcap.records import Attachment, Channel, Message, Metadata, Schema
    from mcap.writer import CompressionType, Writer

    from .mcap_io import LIBRARY, PROFILE, RunContents

    p = Path(path)
    if out_path is None:
        stem = p.name[:-5] if p.name.endswith(".mcap") else p.name
        out_path = p.with_name(stem + ".recovered.mcap")
    q = Path(out_path)
    if q.exists():
        raise InputError(f"{q}: exists already; a run is never overwritten")
    tmp = q.with_name(f".{q.name}.part")
    contents = RunContents()
    scan = Scan()
    n_messages = 0
    try:
        with open(tmp, "xb") as fh:
            w = Writer(fh, chunk_size=1024 * 1024, compression=CompressionType.ZSTD)
            w.start(profile=PROFILE, library=LIBRARY + "-recover")
            schema_map: dict[int, int] = {}
            chan_map: dict[int, int] = {}
            topics: dict[int, str] = {}
            for rec in scan_mcap(p, scan):
                if isinstance(rec, Message):
                    cid = chan_map.get(rec.channel_id)
                    if cid is None:
                        scan.orphans += 1
                        continue
                    w.add_message(cid, rec.log_time, rec.data, rec.publish_time, rec.sequence)
                    contents.messages[topics[rec.channel_id]].append((rec.log_time, {}))
                    n_messages += 1
                elif isinstance(rec, Schema):
                    if rec.id not in schema_map:
                        schema_map[rec.id] = w.register_schema(rec.name, rec.encoding, rec.data)
                elif isinstance(rec, Channel):
                    if rec.id not in chan_map:
                        chan_map[rec.id] = w.register_channel(
                            rec.topic,
                            rec.message_encoding,
                            schema_map.get(rec.schema_id, 0),
                            dict(rec.metadata),
                        )
                        topics[rec.id] = rec.topic
                        contents.messages.setdefault(rec.topic, [])
                elif isinstance(rec, Metadata):
                    w.add_metadata(rec.name, dict(rec.metadata))
                    contents.metadata[rec.name] = dict(rec.metadata)
                elif isinstance(rec, Attachment):
                    w.add_attachment(
                        rec.create_time, rec.log_time, rec.name, rec.media_type, rec.data
                    )
                    contents.attachments[rec.name] = (rec.media_type, b"")
            problems = [f"skipped {d}" for d in scan.skipped]
            if scan.orphans:
                problems.append(
                    f"{scan.orphans} messages dropped: their channel was defined in a damaged part"
                )
            stopped = scan.truncated_reason or ("end of file" if scan.complete else "no footer")
            if n_messages == 0 and not contents.metadata and not contents.attachments:
                why = "; ".join([*problems[:2], stopped])
                raise InputError(f"{p}: nothing to salvage ({why})")
            w.add_metadata(
                "recovery",
                {
                    "source_file": p.name,
                    "source_complete": str(scan.complete).lower(),
                    "stopped_at": stopped,
                    "skipped": json.dumps(problems),
                    "chunks_recovered": str(scan.chunks_ok),
                    "messages": str(n_messages),
                    "recovered_at_ns": str(time.time_ns()),
                },
            )
            w.finish()
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, q)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    contents.complete = scan.complete
    contents.error = "; ".join(x for x in [*problems, scan.truncated_reason] if x) or None
    contents.metadata.setdefault("recovery", {})
    contents.metadata["recovery"] = {
        "stopped_at": stopped,
        "skipped": json.dumps(problems),
        "messages": str(n_messages),
    }
    return q, contents
