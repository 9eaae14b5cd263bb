"""``open_run(path)``: the one columnar reader of run files (MCAP).

A :class:`Run` gives the metadata records, the attachments, a description of every stream (schema,
fields with units and shapes, message count, exact time range) and, for the topics asked for only,
a ``pandas.DataFrame`` per topic: ``run.table("/tensions")``, or window by window for runs larger
than memory: ``for df in run.iter_tables("/tensions", window_ns=60 * 10**9)``.

The reader goes through the MCAP summary: the chunk index says which chunks hold a channel and over
which times, the message index after each chunk says where each message of the channel sits in it,
so a topic is read without decoding the others.  Bodies are decoded a chunk at a time: flat numeric
JSON (tensions, tunnel, the recorder's stats) by one regular-expression pass and one numpy
conversion per chunk, the rest by one ``json.loads`` of the chunk's bodies joined into a JSON array.
Nothing outside this module knows the message layout: the columns are

- ``t_ns`` (int64, the message log time, ns since the Unix epoch) first, sorted;
- pose (``foxglove.PoseInFrame``): ``x_m, y_m, z_m, qw, qx, qy, qz``, then ``cov_00 .. cov_55``
  when a covariance was recorded, then the other recorded values (``reprojection_px``, ``flags``,
  ``status``, ``frame_id``, ...; a list value ``v`` of length k becomes ``v_0 .. v_{k-1}``);
- events (``foxglove.Log``): ``level``, ``message``, ``name`` and the extra fields;
- raw CAN frames (``/can_raw``): one column per recorded field, ``data`` as ``bytes``;
- every other stream: its fields as recorded (``T_<cable>_N``, ``status``, ``counter``, ...).
  A missing number (JSON ``null``, which the writer writes for NaN) is NaN.

A file without a valid summary (a recorder killed mid-run) is read through
:func:`cdpr.daq.mcap_io.recover_run` into a temporary file, with the same API: ``run.recovered`` is
True and ``run.warning`` says what was lost.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import struct
import tempfile
import warnings
import zlib
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from cdpr.analysis.errors import CdprError, InputError

from . import column_blocks

__all__ = ["FieldInfo", "Run", "StreamInfo", "open_run"]

_MAGIC = b"\x89MCAP0\r\n"
_KEY = re.compile(rb'"(?:[^"\\]|\\.)*":')
_U64 = np.dtype("<u8")
_NULLABLE_TEXT = {"channel", "frame_id", "message", "name"}


@dataclass(frozen=True)
class FieldInfo:
    """A field of a stream as its schema describes it: JSON type, unit and shape (``()`` scalar)."""

    type: str
    unit: str = ""
    shape: tuple[int, ...] = ()


@dataclass
class StreamInfo:
    """One stream of a run: topic, schema name, fields, nominal rate, message count and time range
    (``start_ns``/``stop_ns`` of its first and last message, None when it has none)."""

    topic: str
    schema_name: str
    fields: dict[str, FieldInfo]
    rate_hz: float
    count: int
    start_ns: int | None
    stop_ns: int | None
    metadata: dict[str, str] = field(default_factory=dict)

    @property
    def units(self) -> dict[str, str]:
        return {k: f.unit for k, f in self.fields.items() if f.unit}


def _fields_of(schema: dict[str, Any] | None, units: dict[str, str]) -> dict[str, FieldInfo]:
    out: dict[str, FieldInfo] = {}
    props = (schema or {}).get("properties", {})
    for name, p in props.items():
        if not isinstance(p, dict) or name == "timestamp":
            continue
        shape: list[int] = []
        q = p
        while q.get("type") == "array" and "minItems" in q and isinstance(q.get("items"), dict):
            shape.append(int(q["minItems"]))
            q = q["items"]
        typ = q.get("type", "object")
        if isinstance(typ, list):  # ["number", "null"]: a number that may be missing
            typ = next((t for t in typ if t != "null"), "null")
        unit = units.get(name, "")
        desc = str(p.get("description", ""))
        if not unit and desc.startswith("unit: "):
            unit = desc[6:].split(";")[0]
        out[name] = FieldInfo(str(typ), unit, tuple(shape))
    return out


def _in_window(t: np.ndarray, start_ns: int | None, stop_ns: int | None) -> np.ndarray:
    """(n,) bool: ``start_ns <= t < stop_ns`` (None: no bound on that side)."""
    keep = np.ones(len(t), bool)
    if start_ns is not None:
        keep &= t >= start_ns
    if stop_ns is not None:
        keep &= t < stop_ns
    return keep


def _block_fields(text: str) -> dict[str, FieldInfo]:
    """Per-sample fields of a block channel from its ``fields`` metadata (name -> [dtype, unit])."""
    try:
        spec = json.loads(text)
    except ValueError:
        spec = {}
    out: dict[str, FieldInfo] = {}
    for name, v in (spec if isinstance(spec, dict) else {}).items():
        dt, unit = (v + ["", ""])[:2] if isinstance(v, list) else ("", "")
        out[str(name)] = FieldInfo("integer" if dt == "<i8" else "number", str(unit))
    return out


class DamagedRunError(InputError):
    """A part of a run file that its summary points at cannot be read (a chunk with bad compression
    or CRC, a message index, a metadata record or an attachment that does not parse): open the file
    with ``open_run(path, recover=True)`` to read what the recovery path salvages, or run
    ``cdpr recover``."""


@contextmanager
def _damage_is_one_line(path: Path, what: str) -> Iterator[None]:
    """Any failure while reading ``what`` of ``path`` (a damaged length, name or body makes
    ``struct``, the UTF-8 decoder, ``json``, a decompressor ... fail) becomes one
    :class:`DamagedRunError` naming the file and the part, never a traceback."""
    try:
        yield
    except CdprError:
        raise
    except Exception as exc:
        why = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
        raise DamagedRunError(
            f"{path}: damaged {what} ({why}); `cdpr recover` keeps every readable chunk"
        ) from None


class Run:
    """An open run file (see the module docstring); use :func:`open_run`."""

    def __init__(self, path: Path, recover: bool = False) -> None:
        self.path = path
        self.recovered = False
        self.warning: str | None = None
        self._tmpdir: str | None = None
        self._chunk_cache: dict[int, bytes] = {}
        self._verified: set[int] = set()  # chunks whose CRC was checked (start offsets)
        self._fh = path.open("rb")
        self._size = os.fstat(self._fh.fileno()).st_size
        try:
            with _damage_is_one_line(path, "run file"):
                self._load(recover)
        except BaseException:
            self.close()
            raise

    def _load(self, recover: bool) -> None:
        from mcap.exceptions import McapError
        from mcap.reader import SeekingReader

        path = self.path
        summary = None
        why = ""
        try:
            summary = SeekingReader(self._fh).get_summary()
        except (McapError, struct.error, ValueError, EOFError, OSError):
            summary = None  # too short for a footer, or a bad one: recovery reads what is there
        if summary is not None:
            why = self._footer_problem()
        if (
            recover
            or summary is None
            or why
            or (
                summary.statistics
                and summary.statistics.message_count
                and not summary.chunk_indexes
            )
        ):
            self._fh.close()
            self._open_recovered(path, why)
            summary = self._summary_of_recovered()
        self._summary = summary
        self.metadata: dict[str, dict[str, str]] = {}
        for mi in summary.metadata_indexes:
            self.metadata[mi.name] = self._read_metadata(mi.offset, mi.length)
        self._attachment_index = {ai.name: ai for ai in summary.attachment_indexes}
        self._attachments: dict[str, tuple[str, bytes]] | None = None
        counts = dict(summary.statistics.channel_message_counts) if summary.statistics else {}
        self._topic_cid: dict[str, int] = {}
        self._blocked: set[int] = set()  # channels stored as column blocks
        self._frame_blocks: set[int] = set()  # those of raw CAN frames (layout can_frames)
        self._block_indexes: dict[tuple[int, int], np.ndarray] = {}  # their message indexes
        self.streams: dict[str, StreamInfo] = {}
        for cid, ch in sorted(summary.channels.items()):
            sch = summary.schemas.get(ch.schema_id)
            schema_json = None
            if sch is not None and sch.encoding == "jsonschema":
                try:
                    schema_json = json.loads(sch.data)
                except ValueError:
                    schema_json = None
            meta = dict(ch.metadata)
            try:
                units = json.loads(meta.get("units", "{}"))
            except ValueError:
                units = {}
            try:
                rate = float(meta.get("rate_hz", "0") or 0)
            except ValueError:
                rate = 0.0
            self._topic_cid[ch.topic] = cid
            if meta.get("storage") == column_blocks.STORAGE and meta.get("layout") == "can_frames":
                from .can_raw import schema as frame_schema

                self._blocked.add(cid)
                self._frame_blocks.add(cid)
                stream = meta.get("stream", ch.topic.lstrip("/"))
                fields = _fields_of(frame_schema(stream), units if isinstance(units, dict) else {})
            elif meta.get("storage") == column_blocks.STORAGE:
                self._blocked.add(cid)
                fields = _block_fields(meta.get("fields", "{}"))
            else:
                fields = _fields_of(schema_json, units if isinstance(units, dict) else {})
            schema_name = sch.name if sch is not None else ""
            if cid in self._blocked:  # the per-sample schema (the view's), not the block's
                schema_name = f"cdpr.{meta.get('stream', ch.topic.lstrip('/'))}"
            self.streams[ch.topic] = StreamInfo(
                ch.topic,
                schema_name,
                fields,
                rate,
                int(counts.get(cid, 0)),
                None,
                None,
                meta,
            )
            info = self.streams[ch.topic]
            if cid in self._blocked:
                info.count, info.start_ns, info.stop_ns = self._block_extent(cid)
            else:
                info.start_ns, info.stop_ns = self._time_range(cid)
        self._pair_status_channels()

    def _pair_status_channels(self) -> None:
        """A stream written as two channels (a pose: ``/pose`` in Foxglove's ``PoseInFrame`` for
        the frames with a pose, ``/pose_status`` with metadata ``status_of = /pose`` for every
        frame) is one stream here: ``streams["/pose"]`` counts the frames and has the fields of
        both, ``table("/pose")`` joins them (:func:`_join_status`)."""
        self._status_topic: dict[str, str] = {}  # topic -> its status topic
        for topic, info in list(self.streams.items()):
            of = info.metadata.get("status_of", "")
            main = self.streams.get(of)
            if main is None or of == topic or of in self._status_topic:
                continue
            self._status_topic[of] = topic
            self.streams[of] = StreamInfo(
                of,
                main.schema_name,
                {**main.fields, **info.fields},
                main.rate_hz or info.rate_hz,
                info.count,
                info.start_ns,
                info.stop_ns,
                {**main.metadata, "status_topic": topic},
            )

    # -- opening ------------------------------------------------------------------------------
    def _footer_problem(self) -> str:
        """What is wrong with the footer and summary section (:func:`cdpr.daq.recover.footer_check`:
        the closing magic, the summary offsets, the summary CRC); "" when nothing."""
        import mmap

        from .recover import footer_check

        if self._size < 8:
            return "the file is too short for a footer"
        with mmap.mmap(self._fh.fileno(), 0, access=mmap.ACCESS_READ) as buf:
            return footer_check(buf, self._size)[1]

    def _open_recovered(self, path: Path, why: str = "") -> None:
        from .mcap_io import recover_run

        self._tmpdir = tempfile.mkdtemp(prefix="cdpr-run-")
        out = Path(self._tmpdir) / (path.name.removesuffix(".mcap") + ".recovered.mcap")
        _, contents = recover_run(path, out)
        n = sum(len(v) for v in contents.messages.values())
        self.recovered = True
        lost = contents.error or "no footer"
        if why and why not in lost:
            lost = f"{why}; {lost}"
        self.warning = (
            f"{path}: no valid MCAP summary or a damaged part (truncated or damaged: {lost}); "
            f"read through recovery, {n} messages salvaged, the damaged parts are lost"
        )
        self._fh = out.open("rb")
        self._size = os.fstat(self._fh.fileno()).st_size

    def _summary_of_recovered(self) -> Any:
        from mcap.reader import SeekingReader

        summary = SeekingReader(self._fh).get_summary()
        if summary is None:  # recover_run always writes a summary
            raise InputError(f"{self.path}: recovery produced no summary")
        return summary

    def close(self) -> None:
        """Close the file (and remove the recovered copy of a truncated run)."""
        self._fh.close()
        self._chunk_cache.clear()
        if self._tmpdir is not None:
            shutil.rmtree(self._tmpdir, ignore_errors=True)
            self._tmpdir = None

    def __enter__(self) -> Run:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- records ------------------------------------------------------------------------------
    def _read_at(self, offset: int, length: int) -> bytes:
        if offset < 0 or length < 0 or offset + length > self._size:
            raise DamagedRunError(
                f"{self.path}: the summary points at {length} bytes at offset {offset}, past the "
                f"end of the file ({self._size} bytes); `cdpr recover` keeps every readable chunk"
            )
        self._fh.seek(offset)
        data = self._fh.read(length)
        if len(data) != length:
            raise DamagedRunError(f"{self.path}: record at byte {offset} cut short")
        return data

    def _read_metadata(self, offset: int, length: int) -> dict[str, str]:
        with _damage_is_one_line(self.path, f"metadata record at byte {offset}"):
            return self._parse_metadata(offset, length)

    def _parse_metadata(self, offset: int, length: int) -> dict[str, str]:
        """The key/value map of the metadata record at ``offset``: opcode 0x0C, u64 length, name,
        u32 byte length of the map, then (u32 length, key, u32 length, value) pairs that fill the
        record exactly (anything else is damage)."""
        raw = self._read_at(offset, length)
        if length < 17 or raw[0] != 0x0C or struct.unpack_from("<Q", raw, 1)[0] != length - 9:
            raise DamagedRunError(
                f"{self.path}: damaged metadata record at byte {offset} (not the record of "
                f"{length} bytes the summary's index points at); `cdpr recover` keeps every "
                "readable chunk"
            )

        def text(pos: int) -> tuple[str, int]:
            (n,) = struct.unpack_from("<I", raw, pos)
            if pos + 4 + n > length:
                raise ValueError(f"a string of {n} bytes at {pos} runs past the record")
            return raw[pos + 4 : pos + 4 + n].decode(), pos + 4 + n

        _, pos = text(9)
        (mlen,) = struct.unpack_from("<I", raw, pos)
        pos += 4
        if pos + mlen != length:
            raise ValueError(f"its map of {mlen} bytes does not fill the record")
        out: dict[str, str] = {}
        while pos < length:
            k, pos = text(pos)
            out[k], pos = text(pos)
        return out

    @property
    def attachments(self) -> dict[str, tuple[str, bytes]]:
        """Attachment name -> (media type, bytes), read on first use."""
        if self._attachments is None:
            from mcap.data_stream import ReadDataStream
            from mcap.records import Attachment

            out: dict[str, tuple[str, bytes]] = {}
            for name, ai in self._attachment_index.items():
                with _damage_is_one_line(self.path, f"attachment {name!r} at byte {ai.offset}"):
                    raw = self._read_at(ai.offset + 9, ai.length - 9)
                    import io

                    rec = Attachment.read(ReadDataStream(io.BytesIO(raw)))
                    out[name] = (rec.media_type, bytes(rec.data))
            self._attachments = out
        return self._attachments

    def _chunk(self, ci: Any, cache: bool = True) -> bytes:
        """The uncompressed records of the chunk of chunk index ``ci`` (cached: the last few)."""
        hit = self._chunk_cache.get(ci.chunk_start_offset)
        if hit is not None:
            return hit
        with _damage_is_one_line(self.path, f"chunk at byte {ci.chunk_start_offset}"):
            data = self._read_chunk(ci)
        self._verified.add(ci.chunk_start_offset)
        if cache:
            if len(self._chunk_cache) >= 4:
                self._chunk_cache.pop(next(iter(self._chunk_cache)))
            self._chunk_cache[ci.chunk_start_offset] = data
        return data

    def _read_chunk(self, ci: Any) -> bytes:
        raw = self._read_at(ci.chunk_start_offset, ci.chunk_length)
        if raw[0] != 0x06:
            raise DamagedRunError(f"{self.path}: no chunk record at byte {ci.chunk_start_offset}")
        # opcode, length, start, end, uncompressed size, crc, compression string, records length
        pos = 9 + 24
        (crc,) = struct.unpack_from("<I", raw, pos)
        (clen,) = struct.unpack_from("<I", raw, pos + 4)
        compression = raw[pos + 8 : pos + 8 + clen].decode()
        pos += 8 + clen
        (rlen,) = struct.unpack_from("<Q", raw, pos)
        body = raw[pos + 8 : pos + 8 + rlen]
        # zstandard.ZstdError, lz4's RuntimeError: the chunk is damaged (_damage_is_one_line)
        data = _decompress(compression, body, ci.uncompressed_size)
        if data is None:
            raise DamagedRunError(
                f"{self.path}: chunk at byte {ci.chunk_start_offset}: "
                f"unknown compression {compression!r}"
            )
        if crc and zlib.crc32(data) != crc:
            raise DamagedRunError(
                f"{self.path}: damaged chunk at byte {ci.chunk_start_offset}: CRC mismatch; "
                "`cdpr recover` keeps every readable chunk"
            )
        if len(data) != ci.uncompressed_size:
            raise DamagedRunError(
                f"{self.path}: damaged chunk at byte {ci.chunk_start_offset}: {len(data)} bytes "
                f"uncompressed, the summary says {ci.uncompressed_size}"
            )
        return data

    def verify(self) -> None:
        """Check every chunk the summary lists (decompressed, CRC) and its message indexes,
        without keeping them; raises :class:`DamagedRunError` at the first damaged one.  Chunks
        already read are not read again."""
        for ci in self._summary.chunk_indexes:
            if ci.chunk_start_offset not in self._verified:
                self._chunk(ci, cache=False)
            for cid in ci.message_index_offsets:
                self._message_index(ci, cid)

    def _message_index(self, ci: Any, cid: int) -> np.ndarray:
        """(k, 2) uint64 (log_time, offset in the chunk) of channel ``cid`` in chunk ``ci``."""
        off = ci.message_index_offsets.get(cid)
        if off is None:
            return np.empty((0, 2), _U64)
        with _damage_is_one_line(self.path, f"message index at byte {off}"):
            return self._read_message_index(ci, cid, off)

    def _read_message_index(self, ci: Any, cid: int, off: int) -> np.ndarray:
        head = self._read_at(off, 15)
        # message index record: opcode 0x07, u64 length, u16 channel, u32 entries byte length
        if len(head) < 15 or head[0] != 0x07 or struct.unpack_from("<H", head, 9)[0] != cid:
            raise self._damaged(off, "not a message index of its channel")
        (blen,) = struct.unpack_from("<I", head, 11)
        raw = self._read_at(off + 15, blen)
        if blen % 16 or len(raw) != blen:
            raise self._damaged(off, "message index cut or of a bad length")
        idx = np.frombuffer(raw, _U64).reshape(-1, 2)
        if len(idx) and int(idx[:, 1].max()) >= ci.uncompressed_size:
            raise self._damaged(off, "message index points outside its chunk")
        return idx

    def _damaged(self, offset: int, what: str) -> DamagedRunError:
        return DamagedRunError(
            f"{self.path}: damaged index at byte {offset} ({what}); "
            "`cdpr recover` keeps every readable chunk"
        )

    def _chunks_of(self, cid: int, start_ns: int | None, stop_ns: int | None) -> list[Any]:
        out = [
            ci
            for ci in self._summary.chunk_indexes
            if cid in ci.message_index_offsets
            and (start_ns is None or ci.message_end_time >= start_ns)
            and (stop_ns is None or ci.message_start_time < stop_ns)
        ]
        out.sort(key=lambda c: (c.message_start_time, c.chunk_start_offset))
        return out

    def _time_range(self, cid: int) -> tuple[int | None, int | None]:
        chunks = self._chunks_of(cid, None, None)
        if not chunks:
            return None, None
        # a chunk's start/end times cover every channel in it: the chunk that ends last may hold
        # only early messages of this channel (streams written in blocks), so look at chunks in
        # order of their end (start) time until none can hold a later (earlier) message
        hi = lo = None
        for c in sorted(chunks, key=lambda c: -c.message_end_time):
            if hi is not None and c.message_end_time <= hi:
                break
            t = self._message_index(c, cid)[:, 0]
            if len(t):
                hi = max(hi or 0, int(t.max()))
        for c in sorted(chunks, key=lambda c: c.message_start_time):
            if lo is not None and c.message_start_time >= lo:
                break
            t = self._message_index(c, cid)[:, 0]
            if len(t):
                lo = int(t.min()) if lo is None else min(lo, int(t.min()))
        return lo, hi

    # -- columnar data --------------------------------------------------------------------------
    def _cid(self, topic: str) -> int:
        cid = self._topic_cid.get(topic)
        if cid is None:
            raise InputError(
                f"{self.path}: no topic {topic!r} in the run (topics: {', '.join(self.streams)})"
            )
        return cid

    def _bodies(
        self, cid: int, start_ns: int | None, stop_ns: int | None
    ) -> Iterator[tuple[np.ndarray, list[bytes]]]:
        """Per chunk: log times (int64) and bodies of channel ``cid`` in [start_ns, stop_ns)."""
        for ci in self._chunks_of(cid, start_ns, stop_ns):
            idx = self._message_index(ci, cid)
            if not len(idx):
                continue
            t = idx[:, 0].astype(np.int64)
            keep = _in_window(t, start_ns, stop_ns)
            if not keep.all():
                idx, t = idx[keep], t[keep]
                if not len(t):
                    continue
            yield t, self._extract(ci, idx)

    def _extract(self, ci: Any, idx: np.ndarray) -> list[bytes]:
        """The bodies of the messages at ``idx[:, 1]`` (offsets) in chunk ``ci``."""
        data = self._chunk(ci)
        buf = np.frombuffer(data, np.uint8)
        off = idx[:, 1].astype(np.int64)
        # message record: opcode, u64 length, u16 channel, u32 sequence, u64 log, u64 publish
        if int(off.max()) + 31 > len(buf) or (buf[off] != 0x05).any():
            raise self._damaged(ci.chunk_start_offset, "a message offset is not a message")
        lens = buf[(off + 1)[:, None] + np.arange(8)].copy().view(_U64).ravel().astype(np.int64)
        starts = off + 31
        ends = off + 9 + lens
        if (lens < 22).any() or int(ends.max()) > len(buf):
            raise self._damaged(ci.chunk_start_offset, "a message runs past its chunk")
        return [data[a:b] for a, b in zip(starts.tolist(), ends.tolist(), strict=True)]

    def _block_index(self, cid: int, start_ns: int | None, stop_ns: int | None) -> list[Any]:
        """The blocks of block channel ``cid`` that hold samples in [start_ns, stop_ns), in time
        order, as (chunk index, (k, 2) index rows) per chunk.  A block's log time is its last
        sample: the blocks needed run from the first with log time >= start_ns to the first with
        log time >= stop_ns, inclusive (message indexes only, nothing decompressed)."""
        rows = []
        past: int | None = None  # the least log time >= stop_ns seen so far
        for ci in self._chunks_of(cid, start_ns, None):
            if past is not None and ci.message_start_time > past:
                break  # chunks come by start time: none after this holds an earlier block
            key = (ci.chunk_start_offset, cid)
            idx = self._block_indexes.get(key)
            if idx is None:
                idx = self._block_indexes[key] = self._message_index(ci, cid)
            if len(idx):
                rows.append((ci, idx))
                if stop_ns is not None:
                    late = idx[:, 0][idx[:, 0] >= stop_ns]
                    if len(late):
                        m = int(late.min())
                        past = m if past is None else min(past, m)
        if not rows:
            return []
        t = np.concatenate([idx[:, 0] for _, idx in rows]).astype(np.int64)
        which = np.concatenate([np.full(len(idx), i) for i, (_, idx) in enumerate(rows)])
        order = np.argsort(t, kind="stable")
        t, which = t[order], which[order]
        pos = np.concatenate([np.arange(len(idx)) for _, idx in rows])[order]
        lo = 0 if start_ns is None else int(np.searchsorted(t, start_ns, "left"))
        hi = len(t) if stop_ns is None else int(np.searchsorted(t, stop_ns, "left")) + 1
        out = []
        sel_w, sel_p = which[lo:hi], pos[lo:hi]
        for i in dict.fromkeys(sel_w.tolist()):
            ci, idx = rows[i]
            out.append((ci, idx[np.sort(sel_p[sel_w == i])]))
        return out

    def _block_columns(
        self,
        cid: int,
        start_ns: int | None,
        stop_ns: int | None,
        columns: Sequence[str] | None = None,
    ) -> dict[str, np.ndarray]:
        """Columns (``t_ns`` first; ``columns``: only these) of the samples of block channel
        ``cid`` in [start_ns, stop_ns), sorted by time; raw CAN frames as their per-frame
        fields."""
        frames = cid in self._frame_blocks
        wanted: Any = columns
        if frames and columns is not None:
            from .can_raw import block_columns_of

            wanted = block_columns_of(columns)
        # a chunk at a time: only the columns asked for outlive their chunk's bytes
        parts = [
            column_blocks.decode_blocks(self._extract(ci, idx), str(self.path), wanted)
            for ci, idx in self._block_index(cid, start_ns, stop_ns)
        ]
        cols = column_blocks.concat(parts) if parts else column_blocks.decode_blocks([])
        keep = _in_window(cols["t_ns"], start_ns, stop_ns)
        if not keep.all():
            cols = {k: v[keep] for k, v in cols.items()}
        if len(cols["t_ns"]) > 1 and np.any(np.diff(cols["t_ns"]) < 0):
            order = np.argsort(cols["t_ns"], kind="stable")
            cols = {k: v[order] for k, v in cols.items()}
        if frames and len(cols["t_ns"]):
            from .can_raw import frames_from_blocks

            try:
                cols = frames_from_blocks(cols)
            except (KeyError, ValueError) as exc:
                raise InputError(
                    f"{self.path}: a block of CAN frames is malformed ({exc})"
                ) from None
        return cols

    def _block_extent(self, cid: int) -> tuple[int, int | None, int | None]:
        """(samples, first, last sample time) of block channel ``cid`` from its first and last
        blocks."""
        blocks = self._block_index(cid, None, None)
        if not blocks:
            return 0, None, None
        ci0, idx0 = blocks[0]
        ci1, idx1 = blocks[-1]
        first = column_blocks.decode_blocks(self._extract(ci0, idx0[:1]), str(self.path))
        last_body = self._extract(ci1, idx1[-1:])
        last = column_blocks.decode_blocks(last_body, str(self.path))
        head = json.loads(last_body[0][: last_body[0].index(b',"data"')] + b"}")
        return (
            int(head["first_sample"]) + int(head["count"]),
            int(first["t_ns"][0]),
            int(last["t_ns"].max()),
        )

    def _decode(self, topic: str, t: np.ndarray, bodies: list[bytes]) -> Any:
        schema = self.streams[topic].schema_name
        df = None
        if "is_fd" in self.streams[topic].fields and "arbitration_id" in self.streams[topic].fields:
            df = _can_frames(bodies)  # raw CAN frames: the writer's fixed-width rows by numpy
        if df is None and schema not in (
            "foxglove.PoseInFrame",
            "foxglove.Log",
            "foxglove.CompressedImage",
        ):
            df = _flat_numeric(bodies, self.streams[topic].fields)
        if df is None:
            with _damage_is_one_line(self.path, f"messages of {topic}"):
                rows = json.loads(b"[" + b",".join(bodies) + b"]")
            df = _rows_frame(rows, schema)
        df.insert(0, "t_ns", t)
        return df

    def times(self, topic: str) -> np.ndarray:
        """The log times (int64 ns, sorted) of every message of ``topic``, from the message indexes
        alone (no chunk is decompressed)."""
        topic = self._status_topic.get(topic, topic)  # a pose stream: every frame
        cid = self._cid(topic)
        if cid in self._blocked:
            return self._block_columns(cid, None, None, ())["t_ns"]
        parts = [self._message_index(ci, cid)[:, 0] for ci in self._chunks_of(cid, None, None)]
        t = np.concatenate(parts).astype(np.int64) if parts else np.empty(0, np.int64)
        t.sort(kind="stable")
        return t

    def table(
        self,
        topic: str,
        columns: Sequence[str] | None = None,
        start_ns: int | None = None,
        stop_ns: int | None = None,
    ) -> Any:
        """The messages of ``topic`` with ``start_ns <= t_ns < stop_ns`` as a DataFrame sorted by
        ``t_ns`` (``columns``: only these, after ``t_ns``; a column no message has is an error).
        A pose stream written with its status channel (``/pose`` + ``/pose_status``) gives one row
        per frame, with or without a pose (:func:`_join_status`)."""
        status = self._status_topic.get(topic)
        if status is not None:
            df = _join_status(
                self._channel_table(topic, None, start_ns, stop_ns),
                self._channel_table(status, None, start_ns, stop_ns),
            )
            return self._finish_frame(topic, df, columns)
        return self._channel_table(topic, columns, start_ns, stop_ns)

    def _channel_table(
        self,
        topic: str,
        columns: Sequence[str] | None,
        start_ns: int | None,
        stop_ns: int | None,
    ) -> Any:
        """:meth:`table` of one channel, as its messages are."""
        import pandas as pd

        cid = self._cid(topic)
        if cid in self._blocked:
            cols = self._block_columns(cid, start_ns, stop_ns, columns)
            if columns is not None:  # only the columns asked for (t_ns always)
                keep = {"t_ns", *columns}
                cols = {k: v for k, v in cols.items() if k in keep}
                if len(cols["t_ns"]) and (missing := [c for c in columns if c not in cols]):
                    raise InputError(
                        f"{self.path}: topic {topic!r} has no column {missing[0]!r} "
                        f"(columns: {', '.join(self.streams[topic].fields)})"
                    )
            df = pd.DataFrame(cols, copy=False)
            for c in _NULLABLE_TEXT & set(df.columns) if cid in self._frame_blocks else ():
                df[c] = pd.Series(cols[c], dtype=object, index=df.index)  # as recorded
            return self._finish_frame(topic, df, columns)
        parts = [self._decode(topic, t, b) for t, b in self._bodies(cid, start_ns, stop_ns)]
        if parts:
            df = pd.concat(parts, ignore_index=True, sort=False) if len(parts) > 1 else parts[0]
        else:
            df = pd.DataFrame({"t_ns": np.empty(0, np.int64)})
        return self._finish_frame(topic, df, columns)

    def _finish_frame(self, topic: str, df: Any, columns: Sequence[str] | None) -> Any:
        t = df["t_ns"].to_numpy()
        if len(t) > 1 and np.any(np.diff(t) < 0):
            df = df.iloc[np.argsort(t, kind="stable")].reset_index(drop=True)
        if columns is not None:
            missing = [c for c in columns if c not in df.columns]
            if missing and len(df):
                raise InputError(
                    f"{self.path}: topic {topic!r} has no column {missing[0]!r} "
                    f"(columns: {', '.join(map(str, df.columns))})"
                )
            df = df.reindex(columns=["t_ns", *[c for c in columns if c != "t_ns"]])
        return df

    def iter_tables(
        self,
        topic: str,
        window_ns: int,
        columns: Sequence[str] | None = None,
        start_ns: int | None = None,
        stop_ns: int | None = None,
    ) -> Iterator[Any]:
        """``table(topic)`` in consecutive time windows of ``window_ns`` (bounded memory): each
        message comes in exactly one window; empty windows are skipped."""
        window_ns = int(window_ns)
        if window_ns <= 0:
            raise InputError(f"window_ns must be > 0, got {window_ns}")
        info = self.streams.get(topic)
        self._cid(topic)
        if info is None or info.start_ns is None or info.stop_ns is None:
            return
        a = info.start_ns if start_ns is None else max(int(start_ns), info.start_ns)
        end = info.stop_ns + 1 if stop_ns is None else min(int(stop_ns), info.stop_ns + 1)
        while a < end:
            b = min(a + window_ns, end)
            df = self.table(topic, columns, a, b)
            if len(df):
                yield df
            a = b

    def __repr__(self) -> str:
        extra = ", recovered" if self.recovered else ""
        return f"Run({str(self.path)!r}, {len(self.streams)} streams{extra})"


#: the columns a pose message gives (:func:`_pose_frame`), in the reader's order
_POSE_COLUMNS = ("x_m", "y_m", "z_m", "qw", "qx", "qy", "qz")


def _rank_in_time(t: np.ndarray) -> np.ndarray:
    """(n,) the position of each entry among the entries of equal time (``t`` sorted)."""
    if not len(t):
        return np.zeros(0, np.int64)
    first = np.r_[0, np.flatnonzero(np.diff(t)) + 1]
    return np.arange(len(t)) - np.repeat(first, np.diff(np.r_[first, len(t)]))


def _join_status(pose: Any, status: Any) -> Any:
    """One row per status message (every frame, sorted by time): ``t_ns``, the pose columns
    (``x_m .. qz``; NaN, and ``frame_id`` None, for a frame without a pose), ``cov_*``,
    ``frame_id``, then the other status columns, as the old one-channel layout gave them.  A
    pose message belongs to the status message of the same log time (among several of one time,
    in order, to those with ``has_pose`` = 1); one whose status message was lost (a damaged chunk
    salvaged) is left out: the status channel is the list of frames."""
    import pandas as pd

    ts = status["t_ns"].to_numpy(np.int64)
    has = (
        np.nan_to_num(status["has_pose"].to_numpy(np.float64)) == 1
        if "has_pose" in status
        else np.ones(len(ts), bool)
    )
    rows = np.flatnonzero(has)
    tp = pose["t_ns"].to_numpy(np.int64)
    left = pd.DataFrame({"t": ts[rows], "r": _rank_in_time(ts[rows]), "i": rows})
    right = pd.DataFrame({"t": tp, "r": _rank_in_time(tp), "j": np.arange(len(tp))})
    pairs = left.merge(right, on=["t", "r"], how="inner")
    i, j = pairs["i"].to_numpy(np.int64), pairs["j"].to_numpy(np.int64)
    cols: dict[str, Any] = {"t_ns": ts}
    for c in _POSE_COLUMNS:
        col = np.full(len(ts), np.nan)
        if c in pose:
            col[i] = pose[c].to_numpy(np.float64)[j]
        cols[c] = col
    rest = [c for c in status.columns if c != "t_ns"]
    for c in [c for c in rest if c.startswith("cov_")]:
        cols[c] = status[c].to_numpy()
    frame_id = np.full(len(ts), None, object)
    if "frame_id" in pose:
        frame_id[i] = pose["frame_id"].to_numpy(object)[j]
    cols["frame_id"] = frame_id
    for c in rest:
        if c not in cols:
            cols[c] = status[c].to_numpy()
    df = pd.DataFrame(cols, copy=False)
    df["frame_id"] = pd.Series(frame_id, dtype=object, index=df.index)
    return df


@dataclass
class StreamSummary:
    """Counts and timing of one stream (``cdpr inspect``)."""

    topic: str
    schema: str
    count: int
    first_ns: int | None
    last_ns: int | None
    rate_hz: float
    nominal_rate_hz: float
    gaps: int
    max_gap_s: float
    bad_status: int


def summarize(run: Run) -> list[StreamSummary]:
    """Per-stream counts, rates, gaps and readings with a non-zero ``status``.

    A gap is an interval longer than 3x the larger of the nominal period (channel metadata
    ``rate_hz``) and the 90th-percentile interval (so bursts, e.g. 4 CAN frames per sample, are not
    gaps).  Times come from the message indexes (of a column-block stream: from its blocks, read
    with its status in one pass); ``status`` is decoded window by window."""
    out = []
    for topic, info in run.streams.items():
        if info.metadata.get("status_of") in run.streams:
            continue  # a pose's status channel: its frames are counted under the pose stream
        blocked = info.metadata.get("storage") == column_blocks.STORAGE
        bad = 0
        if blocked:  # times and status in one pass over the blocks, a window at a time
            parts = []
            for df in run.iter_tables(topic, 600 * 10**9, ["status"]):
                parts.append(df["t_ns"].to_numpy(np.int64))
                bad += int(np.count_nonzero(df["status"].fillna(0).to_numpy()))
            t = np.concatenate(parts) if parts else np.empty(0, np.int64)
        else:
            t = run.times(topic)
        n = len(t)
        nominal = info.rate_hz
        if n == 0:
            out.append(StreamSummary(topic, info.schema_name, 0, None, None, 0.0, nominal, 0,
                                     0.0, 0))  # fmt: skip
            continue
        span = (t[-1] - t[0]) / 1e9
        rate = float((n - 1) / span) if span > 0 else 0.0
        gaps, max_gap = 0, 0.0
        if n > 2:
            dt = np.diff(t) / 1e9
            ref = max(1.0 / nominal if nominal > 0 else 0.0, float(np.percentile(dt, 90)))
            if ref > 0:
                gaps = int(np.count_nonzero(dt > 3 * ref))
            max_gap = float(dt.max())
        if not blocked and ("status" in info.fields or info.schema_name.startswith("cdpr.")):
            for df in run.iter_tables(topic, 600 * 10**9):
                if "status" in df.columns:
                    bad += int(np.count_nonzero(df["status"].fillna(0).to_numpy()))
        out.append(StreamSummary(topic, info.schema_name, n, int(t[0]), int(t[-1]), rate,
                                 nominal, gaps, max_gap, bad))  # fmt: skip
    return out


def open_run(path: str | os.PathLike[str], recover: bool = False) -> Run:
    """Open a run file for reading (see the module docstring).  Bad input (missing file, not an
    MCAP file) raises :class:`~cdpr.analysis.errors.ConfigError` naming the file; a damaged chunk
    met while reading raises :class:`DamagedRunError`.  ``recover=True`` reads the file through
    the recovery path (every readable chunk, before and after damage) even when its summary is
    intact; ``run.recovered`` and ``run.warning`` say so."""
    from .mcap_io import _check_file

    return Run(_check_file(path), recover=recover)


def _decompress(compression: str, body: bytes, size: int) -> bytes | None:
    """A chunk's records; None for an unknown compression."""
    if compression == "zstd":
        import zstandard

        return zstandard.ZstdDecompressor().decompress(body, max_output_size=size)
    if compression == "lz4":
        import lz4.frame

        return bytes(lz4.frame.decompress(body))
    if compression == "":
        return bytes(body)
    return None


# -------------------------------------------------------------------------------------------------
# decoding


def _flat_numeric(bodies: list[bytes], types: dict[str, FieldInfo]) -> Any:
    """Columns of flat JSON objects of numbers with the same keys in the same order, or None when
    the bodies are not like that.  Vectorised over the chunk with numpy on the joined bytes: the
    positions of ``:`` start the values, the next ``,`` or ``}`` ends each; the keys before every
    ``:`` are checked to be the first body's keys in order in every row; the values are gathered
    into one fixed-width byte-string array and each column converted at once (``integer`` fields of
    the schema to int64, exactly; others to float64, ``null`` to NaN)."""
    import pandas as pd

    n = len(bodies)
    keys0 = _KEY.findall(bodies[0])
    k = len(keys0)
    if not k or any(b"," in key or b":" in key[:-1] or b"{" in key for key in keys0):
        return None
    text = b",".join(bodies)
    buf = np.frombuffer(text, np.uint8)
    colon = np.flatnonzero(buf == 58)
    if len(colon) != n * k:
        return None
    seps = np.flatnonzero((buf == 44) | (buf == 125))
    ends = seps[np.searchsorted(seps, colon)]  # every value ends at the next ',' or '}'
    # the keys: '"key"' right before each ':', after '{' (first key of a row) or ','
    klen = np.array([len(key) - 1 for key in keys0], np.int64)  # with both quotes
    kstart = colon - np.tile(klen, n)
    lead = np.full(k, 44, np.uint8)
    lead[0] = 123
    if np.any(kstart < 1) or np.any(buf[kstart - 1] != np.tile(lead, n)):
        return None
    kw = int(klen.max())
    expect = np.zeros((k, kw), np.uint8)
    for j, key in enumerate(keys0):
        expect[j, : len(key) - 1] = np.frombuffer(key[:-1], np.uint8)
    kidx = kstart[:, None] + np.arange(kw)
    got = np.where(
        np.arange(kw) < np.tile(klen, n)[:, None], buf[np.minimum(kidx, len(buf) - 1)], 0
    )
    if not np.array_equal(got.reshape(n, k, kw), np.broadcast_to(expect, (n, k, kw))):
        return None
    vlen = ends - colon - 1
    width = int(vlen.max())
    if width < 1 or width > 64:
        return None
    # the values, space-padded to one width, each followed by ',': the text np.fromstring parses
    vidx = (colon + 1)[:, None] + np.arange(width)
    vals = np.full((n * k, width + 1), 44, np.uint8)
    vals[:, :width] = np.where(
        np.arange(width) < vlen[:, None], buf[np.minimum(vidx, len(buf) - 1)], 32
    )
    if np.any((vals == 34) | (vals == 91) | (vals == 123) | (vals == 116) | (vals == 102)):
        return None  # a string, an array, an object, true or false
    null = vals[:, 0] == 110  # 'null' (NaN written by the writer): parsed as 'nan'
    if null.any():
        vals[null, :4] = np.frombuffer(b"nan ", np.uint8)
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)  # text it cannot parse: not silent
        try:
            flat = np.fromstring(vals.tobytes()[:-1], dtype=np.float64, sep=",")  # noqa: NPY201
        except (DeprecationWarning, ValueError):
            return None
    if len(flat) != n * k:
        return None
    table = flat.reshape(n, k)
    digits = vals[:, :width].reshape(n, k, width)
    cols: dict[str, Any] = {}
    for j, key in enumerate(keys0):
        name = key[1:-2].decode()
        fi = types.get(name)
        col = table[:, j]
        if fi is not None and fi.type == "number":
            cols[name] = col
            continue
        ints = _exact_ints(digits[:, j])
        if ints is not None:
            cols[name] = ints
        elif fi is not None and fi.type == "integer":
            return None
        else:
            cols[name] = col
    return pd.DataFrame(cols)


def _right_aligned_ints(chars: np.ndarray) -> np.ndarray | None:
    """int64 of right-aligned, space-padded non-negative decimal integers (n, w); None when a field
    holds anything else (or a space after a digit)."""
    d = chars.astype(np.int64) - 48
    pad = chars == 32
    if not np.all(((d >= 0) & (d <= 9)) | pad) or np.any(~pad[:, :-1] & pad[:, 1:]):
        return None
    if np.any(pad[:, -1]):
        return None
    acc = np.zeros(len(chars), np.int64)
    for c in range(chars.shape[1]):
        acc = np.where(pad[:, c], acc, acc * 10 + d[:, c])
    return acc


def _can_frames(bodies: list[bytes]) -> Any:
    """Raw CAN frames written by the writer's batch path (:func:`cdpr.daq.can_raw.encode_columns`:
    one fixed-width template per channel, numbers right-aligned) parsed with numpy; the other
    bodies of the chunk with ``json.loads``; None when there is no such row."""
    import pandas as pd

    from .can_raw import template

    first = json.loads(bodies[0]) if bodies else None
    if not isinstance(first, dict) or "channel" not in first:
        return None
    tpl, pos = template(first["channel"])
    size = len(tpl)
    lens = np.fromiter(map(len, bodies), np.int64, len(bodies))
    cand = np.flatnonzero(lens == size)
    if not len(cand):
        return None
    rows = np.frombuffer(b"".join([bodies[i] for i in cand.tolist()]), np.uint8).reshape(-1, size)
    const = np.frombuffer(tpl.encode(), np.uint8)
    fixed = const != ord("#")
    ok = (rows[:, fixed] == const[fixed]).all(axis=1)
    if not ok.any():
        return None
    rows, cand = rows[ok], cand[ok]
    ids = _right_aligned_ints(rows[:, pos["id"] : pos["id"] + 9])
    t_bus = _right_aligned_ints(rows[:, pos["t"] : pos["t"] + 19])
    ext = rows[:, pos["ext"]].astype(np.int64) - 48
    rx = rows[:, pos["rx"]].astype(np.int64) - 48
    data = np.empty((len(rows), 8), np.int64)
    for j in range(8):
        a = pos["data"] + 4 * j
        v = _right_aligned_ints(rows[:, a : a + 3])
        if v is None:
            return None
        data[:, j] = v
    if (
        ids is None
        or t_bus is None
        or np.any((ext < 0) | (ext > 1) | (rx < 0) | (rx > 1))
        or np.any(data > 255)
    ):
        return None
    k = len(rows)
    zeros = np.zeros(k, np.int64)
    raw = data.astype(np.uint8)
    payload = np.empty(k, object)
    payload[:] = [r.tobytes() for r in raw]
    channel = np.empty(k, object)
    channel[:] = [first["channel"]] * k
    fast = pd.DataFrame(
        {
            "arbitration_id": ids, "is_extended": ext, "is_remote": zeros,
            "is_error_frame": zeros, "is_fd": zeros, "bitrate_switch": zeros,
            "error_state_indicator": zeros, "dlc": zeros + 8, "data": payload,
            "channel": channel, "is_rx": rx, "t_bus_ns": t_bus, "status": zeros,
        },
        index=cand,
    )  # fmt: skip
    if k == len(bodies):
        return fast.reset_index(drop=True)
    rest = np.setdiff1d(np.arange(len(bodies)), cand)
    slow = _rows_frame(json.loads(b"[" + b",".join([bodies[i] for i in rest.tolist()]) + b"]"),
                       "cdpr.can_raw")  # fmt: skip
    slow.index = rest
    for c in ("channel", "data"):
        if c in slow.columns:
            slow[c] = pd.Series(slow[c].to_numpy(object), dtype=object, index=rest)
    both = pd.concat([fast, slow], sort=False).sort_index()
    for c in ("channel", "data"):
        col = np.empty(len(both), object)
        col[:] = both[c].tolist()
        both[c] = pd.Series(col, dtype=object, index=both.index)
    return both.reset_index(drop=True)


def _exact_ints(chars: np.ndarray) -> np.ndarray | None:
    """int64 values of right-space-padded ASCII integers (n, w) (optional leading '-'), exactly;
    None when a value is not an integer of at most 18 digits."""
    if chars.shape[1] > 19:
        if np.any(chars[:, 19:] != 32):  # beyond int64
            return None
        chars = chars[:, :19]
    neg = chars[:, 0] == 45
    d = chars.astype(np.int64) - 48
    d[:, 0] = np.where(neg, 0, d[:, 0])
    pad = chars == 32
    isdig = (d >= 0) & (d <= 9)
    if not np.all(isdig | pad):
        return None
    # digits must be contiguous from the start (then padding): a pad followed by a digit is not
    if np.any(pad[:, :-1] & ~pad[:, 1:]) or np.any(pad[:, 0]):
        return None
    acc = np.zeros(len(chars), np.int64)
    for c in range(chars.shape[1]):
        p = ~pad[:, c]
        acc = np.where(p, acc * 10 + d[:, c], acc)
    return np.where(neg, -acc, acc)


def _flatten(prefix: str, v: Any, out: dict[str, Any]) -> None:
    if isinstance(v, dict):
        for k, x in v.items():
            _flatten(f"{prefix}_{k}" if prefix else str(k), x, out)
    elif isinstance(v, list):
        if prefix == "covariance" and len(v) == 36:
            for i, x in enumerate(v):
                out[f"cov_{i // 6}{i % 6}"] = x
        else:
            for i, x in enumerate(v):
                _flatten(f"{prefix}_{i}", x, out)
    else:
        out[prefix] = v


def _pose_frame(rows: list[dict[str, Any]]) -> Any:
    """``foxglove.PoseInFrame`` rows that all have the same keys in the same order, the extra
    values numbers (or null) or lists of numbers of one length, as columns at once (the same
    columns and values as the row-by-row path); None for anything else."""
    import pandas as pd

    keys = tuple(rows[0])
    if any(tuple(r) != keys for r in rows) or "pose" not in keys:
        return None
    try:
        pose = [r["pose"] for r in rows]
        pos = [p["position"] for p in pose]
        ori = [p["orientation"] for p in pose]
        cols: dict[str, Any] = {
            "x_m": [p["x"] for p in pos], "y_m": [p["y"] for p in pos],
            "z_m": [p["z"] for p in pos], "qw": [q["w"] for q in ori],
            "qx": [q["x"] for q in ori], "qy": [q["y"] for q in ori], "qz": [q["z"] for q in ori],
        }  # fmt: skip
    except (KeyError, TypeError):
        return None
    for name in ("x_m", "y_m", "z_m", "qw", "qx", "qy", "qz"):
        a = np.array(cols[name], dtype=object)
        if not all(v is None or type(v) in (int, float) for v in cols[name]):
            return None
        cols[name] = np.array(np.where(a == None, np.nan, a), dtype=np.float64)  # noqa: E711
    order = (["covariance"] if "covariance" in keys else []) + [
        k for k in keys if k not in ("timestamp", "pose", "covariance")
    ]  # as the row path: the covariance right after the pose
    text: list[str] = []
    for key in order:
        vals = [r[key] for r in rows]
        first = vals[0]
        if key == "covariance" or isinstance(first, list):
            n = len(first) if isinstance(first, list) else -1
            if n < 0 or any(not isinstance(v, list) or len(v) != n for v in vals):
                return None
            try:
                arr = np.array(vals, dtype=np.float64).reshape(len(rows), n)
            except (TypeError, ValueError):
                return None
            names = (
                [f"cov_{i // 6}{i % 6}" for i in range(36)]
                if key == "covariance" and n == 36
                else [f"{key}_{i}" for i in range(n)]
            )
            if any(type(x) is not float for v in vals[:1] for x in v):
                return None  # integers or nulls in a list: the row path keeps their types
            for j, c in enumerate(names):
                cols[c] = arr[:, j]
        elif key in _NULLABLE_TEXT:
            col = np.empty(len(vals), object)
            col[:] = vals
            cols[key] = col
            text.append(key)
        elif all(type(v) is int for v in vals):
            cols[key] = np.array(vals, dtype=np.int64)
        elif all(v is None or type(v) in (int, float) for v in vals):
            if all(v is None for v in vals):
                cols[key] = np.full(len(vals), np.nan)
            else:
                cols[key] = np.array([np.nan if v is None else v for v in vals], np.float64)
        else:
            return None
    df = pd.DataFrame(cols, copy=False)
    for key in text:  # values as recorded (a name, a number or null), as the row path keeps them
        df[key] = pd.Series(cols[key], dtype=object, index=df.index)
    return df


def _rows_frame(rows: list[dict[str, Any]], schema: str) -> Any:
    import base64

    import pandas as pd

    if schema == "foxglove.PoseInFrame" and rows:
        fast = _pose_frame(rows)
        if fast is not None:
            return fast
    flat_rows = []
    for body in rows:
        out: dict[str, Any] = {}
        body = dict(body)
        body.pop("timestamp", None)
        if schema == "foxglove.PoseInFrame":
            pose = body.pop("pose", {}) or {}
            p = pose.get("position", {}) or {}
            q = pose.get("orientation", {}) or {}
            out.update(
                x_m=p.get("x"), y_m=p.get("y"), z_m=p.get("z"),
                qw=q.get("w"), qx=q.get("x"), qy=q.get("y"), qz=q.get("z"),
            )  # fmt: skip
            cov = body.pop("covariance", None)
            if isinstance(cov, list):
                _flatten("covariance", cov, out)
        elif schema == "foxglove.CompressedImage":
            raw = body.pop("data", "")
            out["data"] = base64.b64decode(raw) if isinstance(raw, str) else bytes(raw or b"")
        if "data" in body and isinstance(body["data"], list):  # raw CAN payload
            out["data"] = bytes(body.pop("data"))
        for key, v in body.items():
            _flatten(key, v, out)
        flat_rows.append(out)
    df = pd.DataFrame.from_records(flat_rows)
    for c in df.columns:
        if c in _NULLABLE_TEXT:  # values as recorded (a channel is a name, a number or null)
            col = np.empty(len(flat_rows), object)
            col[:] = [r.get(c) for r in flat_rows]
            df[c] = pd.Series(col, dtype=object, index=df.index)
            continue
        if df[c].dtype == object and df[c].map(lambda x: x is None).all():
            df[c] = np.nan
    return df
