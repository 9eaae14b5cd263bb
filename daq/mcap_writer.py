"""Run files in MCAP, the writing side: :class:`McapRunWriter` (the recorder's writer, with its own
small chunk writer) and the stream codecs (schemas and encoders).

Layout of a run file (see ``docs/recording.md``):

- one channel per stream, topic ``/<stream>``, message encoding ``json``, schema encoding
  ``jsonschema``; a message's ``log_time`` is the reading's ``t_ns`` (host time of reception, ns since
  the Unix epoch) and its JSON body holds the reading's values (flat numeric fields, so a plot panel
  graphs them) plus ``status``;
- Foxglove's well-known schemas where one exists: streams whose name contains ``pose`` use
  ``foxglove.PoseInFrame``, else ``image`` ``foxglove.CompressedImage``; ``event*`` use
  ``foxglove.Log``; drivers register more (:func:`register_stream_codec`: the CAN driver registers
  ``can_raw``, :mod:`cdpr.daq.can_raw`);
- metadata records (``run`` at the start, ``run_end`` at the end) and attachments (rig file,
  calibration files, config file), so a run file is self-contained.

The python ``mcap`` writer closes a chunk only when it outgrows ``chunk_size``;
:class:`McapRunWriter` also closes it when it is older than ``flush_interval_s`` and fsyncs the file,
so a killed recorder loses at most about one flush interval of data.
"""

from __future__ import annotations

import base64
import fnmatch
import json
import math
import os
import struct
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cdpr.analysis.errors import InputError

from . import column_blocks
from .source import Reading, StreamDescription

PROFILE = ""
LIBRARY = "cdpr-recorder"

_JSON_TYPES = {
    "float64": {"type": "number"},
    "float32": {"type": "number"},
    "float": {"type": "number"},
    "int64": {"type": "integer"},
    "int32": {"type": "integer"},
    "int": {"type": "integer"},
    "uint8": {"type": "integer"},
    "bool": {"type": "boolean"},
    "str": {"type": "string"},
    "bytes": {"type": "array", "items": {"type": "integer", "minimum": 0, "maximum": 255}},
}

_TIME_SCHEMA = {
    "type": "object",
    "title": "time",
    "properties": {"sec": {"type": "integer", "minimum": 0}, "nsec": {"type": "integer"}},
}


def _default(obj: Any) -> Any:
    """JSON fallback for numpy scalars and arrays, bytes and other sequences."""
    if isinstance(obj, bytes | bytearray | memoryview):
        return list(bytes(obj))
    tolist = getattr(obj, "tolist", None)
    if tolist is not None:
        return tolist()
    if isinstance(obj, set | frozenset | tuple):
        return list(obj)
    raise TypeError(f"cannot encode {type(obj).__name__} as JSON")


def _sanitize(obj: Any) -> Any:
    """Replace non-finite floats (not valid JSON) by ``None``, recursively."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, Mapping):
        return {k: _sanitize(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_sanitize(v) for v in obj]
    if isinstance(obj, bytes | bytearray | memoryview):
        return list(bytes(obj))
    tolist = getattr(obj, "tolist", None)
    if tolist is not None:
        return _sanitize(tolist())
    return obj


_dumps = json.JSONEncoder(default=_default, separators=(",", ":"), allow_nan=True).encode


def encode_json(body: Mapping[str, Any]) -> bytes:
    """Compact JSON bytes of ``body``; NaN and infinities become ``null`` (strict JSON)."""
    text = _dumps(body)
    if "NaN" in text or "Infinity" in text:
        text = _dumps(_sanitize(body))
    return text.encode()


def ns_to_time(t_ns: int) -> dict[str, int]:
    """Foxglove ``time`` object ``{"sec", "nsec"}`` of an integer ns timestamp."""
    sec, nsec = divmod(int(t_ns), 1_000_000_000)
    return {"sec": sec, "nsec": nsec}


# -------------------------------------------------------------------------------------------------
# codecs: how a stream's readings become JSON messages and which schema describes them


@dataclass
class StreamCodec:
    """Schema and encoder of one stream.

    schema_name: MCAP schema name (``foxglove.PoseInFrame``, ``cdpr.tensions``, ...).
    schema: JSON schema (dict).
    encode: reading -> message body (a dict, encoded to JSON by the writer, or JSON bytes).
    encode_frames: optional batch encoder of raw CAN frames (``can.Message`` objects, see
        :class:`cdpr.daq.can_raw.CanFrameBatch`) -> :class:`FrameRecords`.
    block_layout: the ``layout`` of the stream stored as column blocks when it is added with a
        description and not ``blocks=False`` (its columns written with
        :meth:`McapRunWriter.write_columns`, or by a frame batch's ``frame_block()``; no view),
        e.g. ``can_frames`` (:mod:`cdpr.daq.can_raw`); None: no block layout.
    """

    schema_name: str
    schema: dict[str, Any]
    encode: Callable[[Reading], Any]
    encode_frames: Callable[[Any], FrameRecords] | None = None
    block_layout: str | None = None
    #: with a block layout: readings -> ``(t_ns, columns, status, values)`` for write_columns
    block_rows: Callable[[Sequence[Reading]], Any] | None = None


#: a float that may be missing: NaN is written as JSON ``null`` (strict JSON has no NaN)
_NUMBER_OR_NULL = {"type": ["number", "null"], "description": "null: missing (NaN)"}


def _field_schema(desc: Any) -> dict[str, Any]:
    base = dict(_JSON_TYPES.get(getattr(desc, "dtype", "float64"), {}))
    if base.get("type") == "number":
        base = dict(_NUMBER_OR_NULL)
    shape = tuple(getattr(desc, "shape", ()) or ())
    for n in reversed(shape):
        base = {"type": "array", "items": base, "minItems": n, "maxItems": n}
    unit = getattr(desc, "unit", "")
    if unit:
        base["description"] = f"unit: {unit}" + (
            "; null: missing (NaN)" if "description" in base else ""
        )
    return base


def flat_codec(stream: str, description: StreamDescription | None) -> StreamCodec:
    """The default codec: the reading's values as they are, plus ``status``.

    The schema lists the described fields (type, shape, unit) and allows extra ones.
    """
    props: dict[str, Any] = {}
    if description is not None:
        for name, fd in description.fields.items():
            props[name] = _field_schema(fd)
    props["status"] = {
        "type": "integer",
        "description": "0 = good, else bit field: 1 saturated, 2 slack, 4 stale, 8 bad frame, 16 gap",
    }
    schema = {
        "type": "object",
        "title": f"cdpr.{stream}",
        "description": (description.doc if description is not None else "")
        + " Time is the message log_time (ns since the Unix epoch).",
        "properties": props,
        "additionalProperties": True,
    }

    def encode(r: Reading) -> Mapping[str, Any]:
        body = dict(r.values)
        body["status"] = r.status
        return body

    return StreamCodec(f"cdpr.{stream}", schema, encode)


def _pose_codec(stream: str, description: StreamDescription | None) -> StreamCodec:
    """``foxglove.PoseInFrame``; values ``position_O_m`` (3,), ``quaternion_xyzw`` (4,) or
    ``quaternion_wxyz`` (4,, scalar first), optional ``frame_id`` (default ``"O"``); every other
    value is carried as an extra flat field."""
    schema = {
        "type": "object",
        "title": "foxglove.PoseInFrame",
        "description": "A timestamped pose in a named coordinate frame (cdpr: platform {P} in {O})",
        "properties": {
            "timestamp": _TIME_SCHEMA,
            "frame_id": {"type": "string"},
            "pose": {
                "type": "object",
                "properties": {
                    "position": {
                        "type": "object",
                        "properties": {k: _NUMBER_OR_NULL for k in "xyz"},
                    },
                    "orientation": {
                        "type": "object",
                        "properties": {k: _NUMBER_OR_NULL for k in "xyzw"},
                    },
                },
            },
            "status": {"type": "integer"},
        },
        "additionalProperties": True,
    }

    def encode(r: Reading) -> Mapping[str, Any]:
        v = dict(r.values)
        p = [float(x) for x in v.pop("position_O_m", (math.nan,) * 3)]
        if "quaternion_wxyz" in v:  # the project's convention elsewhere (scalar first)
            w_, x_, y_, z_ = (float(x) for x in v.pop("quaternion_wxyz"))
            q = [x_, y_, z_, w_]
        else:
            q = [float(x) for x in v.pop("quaternion_xyzw", (0.0, 0.0, 0.0, 1.0))]
        body: dict[str, Any] = {
            "timestamp": ns_to_time(r.t_ns),
            "frame_id": str(v.pop("frame_id", "O")),
            "pose": {
                "position": {"x": p[0], "y": p[1], "z": p[2]},
                "orientation": {"x": q[0], "y": q[1], "z": q[2], "w": q[3]},
            },
        }
        body.update(v)
        body["status"] = r.status
        return body

    return StreamCodec("foxglove.PoseInFrame", schema, encode)


def _image_codec(stream: str, description: StreamDescription | None) -> StreamCodec:
    """``foxglove.CompressedImage``; values ``data`` (bytes: JPEG/PNG), ``format`` (``"jpeg"``,
    ``"png"``), optional ``frame_id`` (default ``"camera"``)."""
    schema = {
        "type": "object",
        "title": "foxglove.CompressedImage",
        "description": "A compressed image",
        "properties": {
            "timestamp": _TIME_SCHEMA,
            "frame_id": {"type": "string"},
            "data": {"type": "string", "contentEncoding": "base64"},
            "format": {"type": "string"},
            "status": {"type": "integer"},
        },
        "additionalProperties": True,
    }

    def encode(r: Reading) -> Mapping[str, Any]:
        v = dict(r.values)
        data = bytes(v.pop("data", b""))
        body: dict[str, Any] = {
            "timestamp": ns_to_time(r.t_ns),
            "frame_id": str(v.pop("frame_id", "camera")),
            "data": base64.b64encode(data).decode("ascii"),
            "format": str(v.pop("format", "jpeg")),
        }
        body.update(v)
        body["status"] = r.status
        return body

    return StreamCodec("foxglove.CompressedImage", schema, encode)


LOG_LEVELS = {
    "unknown": 0,
    "debug": 1,
    "info": 2,
    "warning": 3,
    "error": 4,
    "fatal": 5,
    "critical": 5,
}


def _log_codec(stream: str, description: StreamDescription | None) -> StreamCodec:
    """``foxglove.Log``; values ``message`` (str), optional ``level`` (name or 0-5, default info),
    ``name`` (origin, default the stream); other values are kept as extra fields."""
    schema = {
        "type": "object",
        "title": "foxglove.Log",
        "description": "A log message (cdpr: events such as wind on/off, test points, errors)",
        "properties": {
            "timestamp": _TIME_SCHEMA,
            "level": {
                "type": "integer",
                "description": "0 unknown, 1 debug, 2 info, 3 warning, 4 error, 5 fatal",
            },
            "message": {"type": "string"},
            "name": {"type": "string"},
            "file": {"type": "string"},
            "line": {"type": "integer", "minimum": 0},
            "status": {"type": "integer"},
        },
        "additionalProperties": True,
    }

    def encode(r: Reading) -> Mapping[str, Any]:
        v = dict(r.values)
        level = v.pop("level", 2)
        if isinstance(level, str):
            level = LOG_LEVELS.get(level.lower(), 0)
        body: dict[str, Any] = {
            "timestamp": ns_to_time(r.t_ns),
            "level": int(level),
            "message": str(v.pop("message", "")),
            "name": str(v.pop("name", stream)),
            "file": str(v.pop("file", "")),
            "line": int(v.pop("line", 0)),
        }
        body.update(v)
        body["status"] = r.status
        return body

    return StreamCodec("foxglove.Log", schema, encode)


@dataclass
class FrameRecords:
    """Message bodies of a batch of frames, as a codec's ``encode_frames`` returns them: ``ok[i]``
    says frame ``i`` has its body in ``bodies[j]`` (``j`` counts the ok frames; fixed-length rows
    of uint8); the others are encoded one by one from their readings."""

    ok: Any
    bodies: Any


#: batch types whose frames the writer hands to the stream codec's ``encode_frames`` at once
#: (registered by the drivers, e.g. :class:`cdpr.daq.can_raw.CanFrameBatch`)
_FRAME_BATCH_TYPES: set[type] = set()


def register_frame_batch_type(batch_type: type) -> None:
    """Have :meth:`McapRunWriter.write_many` treat ``batch_type`` as a batch of frames: it has
    ``stream``, ``messages``, ``t_ns`` (one per frame), ``others``, ``frame_reading(i)`` and, for
    a block stream, ``frame_block()`` (see :class:`cdpr.daq.can_raw.CanFrameBatch`)."""
    _FRAME_BATCH_TYPES.add(batch_type)


def is_frame_batch(batch: Any) -> bool:
    """True for an instance of a registered frame-batch type (:func:`register_frame_batch_type`)."""
    return type(batch) in _FRAME_BATCH_TYPES


CodecFactory = Callable[[str, "StreamDescription | None"], StreamCodec]
_CODECS: list[tuple[str, CodecFactory]] = [
    ("pose*", _pose_codec),
    ("*pose*", _pose_codec),  # camera_pose, platform_pose, ...
    ("image*", _image_codec),
    ("*image*", _image_codec),  # camera_image, ...
    ("event*", _log_codec),
]


def register_stream_codec(pattern: str, factory: CodecFactory) -> None:
    """Use ``factory(stream, description)`` for streams whose name matches ``pattern`` (fnmatch);
    later registrations win."""
    _CODECS.insert(0, (pattern, factory))


def codec_for(stream: str, description: StreamDescription | None) -> StreamCodec:
    """The codec of ``stream``: the first registered pattern that matches, else :func:`flat_codec`."""
    base = stream.rsplit("/", 1)[-1]
    for pattern, factory in _CODECS:
        if fnmatch.fnmatchcase(base, pattern):
            return factory(stream, description)
    return flat_codec(stream, description)


def topic_of(stream: str) -> str:
    """MCAP topic of a stream: ``/<stream>``."""
    return "/" + stream


# -------------------------------------------------------------------------------------------------
# the low-level writer: MCAP records through the ``mcap`` package's record classes, except messages,
# which are packed here straight into the open chunk (the python writer's per-message objects took
# about 3/4 of the writer's time)

_MAGIC = b"\x89MCAP0\r\n"
#: zstd level of the chunks: 1 (fastest) compressed the benchmark's CAN frames both faster (1.5x) and
#: smaller than the library default 3
ZSTD_LEVEL = 1
_MSG = struct.Struct("<BQHIQQ")  # opcode 0x05, record length, channel, sequence, log/publish time
_OP_MESSAGE = 0x05
_OP_MESSAGE_INDEX = 0x07


class _ChunkedWriter:
    """An MCAP writer (spec v0): header, schemas and channels outside chunks (so every salvaged
    chunk stays decodable), messages in chunks with message indexes, metadata, attachments, and a
    summary section (schemas, channels, statistics, chunk/attachment/metadata indexes, summary
    offsets) written by :meth:`finish`, like the ``mcap`` package's writer."""

    def __init__(
        self, fh: Any, chunk_size: int, compression: str, background: bool = False
    ) -> None:
        from mcap.data_stream import RecordBuilder

        self._fh = fh
        # background: chunks are compressed and written by one thread, in order, while the caller
        # goes on (zstd releases the GIL); every other write waits for them first (drain)
        self._pool: Any = None
        self._pending: list[Any] = []
        if background:
            from concurrent.futures import ThreadPoolExecutor

            self._pool = ThreadPoolExecutor(1, thread_name_prefix="mcap-chunks")
        self._rb = RecordBuilder()
        self._chunk_size = chunk_size
        self._compression = compression
        if compression == "zstd":
            import zstandard

            self._compress: Callable[[bytes], bytes] | None = zstandard.ZstdCompressor(
                level=ZSTD_LEVEL
            ).compress
        elif compression == "lz4":
            import lz4.frame

            self._compress = lz4.frame.compress
        else:
            self._compress = None
        self._schemas: dict[int, Any] = {}
        self._channels: dict[int, Any] = {}
        self._parts: list[bytes] = []
        self._chunk_len = 0
        # channel id -> segments of (log_time, offset) pairs: flat int lists or (k, 2) arrays
        self._chunk_index: dict[int, list[Any]] = {}
        self._chunk_indexes: list[Any] = []
        self._attachment_indexes: list[Any] = []
        self._metadata_indexes: list[Any] = []
        self.channel_message_counts: dict[int, int] = {}
        self.message_count = 0
        self.t_start = 0
        self.t_end = 0
        self.chunk_count = 0

    #: chunks waiting for the background thread at most (bounded memory)
    MAX_PENDING = 32

    def drain(self, keep: int = 0) -> None:
        """Wait until at most ``keep`` chunks are still being written by the background thread (an
        error there is raised here)."""
        while len(self._pending) > keep:
            self._pending.pop(0).result()

    def shutdown(self) -> None:
        """Stop the background thread (after the chunks it has)."""
        if self._pool is not None:
            try:
                self.drain()
            finally:
                self._pool.shutdown()
                self._pool = None

    def _emit(self) -> int:
        """Write the record builder's bytes to the file; returns their length."""
        data = self._rb.end()
        self._fh.write(data)
        return len(data)

    def start(self, profile: str, library: str) -> None:
        from mcap.records import Header

        self._fh.write(_MAGIC)
        Header(profile=profile, library=library).write(self._rb)
        self._emit()

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        from mcap.records import Schema

        self.drain()
        sid = len(self._schemas) + 1
        s = Schema(id=sid, data=data, encoding=encoding, name=name)
        self._schemas[sid] = s
        s.write(self._rb)
        self._emit()
        return sid

    def register_channel(
        self, topic: str, message_encoding: str, schema_id: int, metadata: dict[str, str]
    ) -> int:
        from mcap.records import Channel

        self.drain()
        cid = len(self._channels) + 1
        c = Channel(
            id=cid,
            topic=topic,
            message_encoding=message_encoding,
            schema_id=schema_id,
            metadata=dict(metadata),
        )
        self._channels[cid] = c
        self.channel_message_counts[cid] = 0
        c.write(self._rb)
        self._emit()
        return cid

    def add_message(self, cid: int, t_ns: int, data: bytes, publish_ns: int, seq: int) -> None:
        n = len(data)
        off = self._chunk_len
        parts = self._parts
        parts.append(_MSG.pack(_OP_MESSAGE, 22 + n, cid, seq & 0xFFFFFFFF, t_ns, publish_ns))
        parts.append(data)
        self._chunk_len = off + 31 + n
        idx = self._chunk_index.get(cid)
        if idx is None:
            idx = self._chunk_index[cid] = [[]]
        last = idx[-1]
        if type(last) is not list:
            last = []
            idx.append(last)
        last += (t_ns, off)  # flat (log_time, offset) pairs
        if self._chunk_len > self._chunk_size:
            self.close_chunk()

    def add_messages(self, cid: int, t_ns: Any, bodies: Any, seq0: int) -> None:
        """Messages of one channel with bodies of equal length, at once: ``t_ns`` (n,) int64 log
        (and publish) times, ``bodies`` (n, L) uint8, sequence numbers ``seq0, seq0 + 1, ...``.
        The chunk is closed as soon as it outgrows ``chunk_size``, as with :meth:`add_message`."""
        import numpy as np

        n, body_len = bodies.shape
        rec_len = 31 + body_len
        recs = np.empty((n, rec_len), np.uint8)
        head = np.frombuffer(_MSG.pack(_OP_MESSAGE, 22 + body_len, cid, 0, 0, 0), np.uint8)
        recs[:, :31] = head
        seq = (np.arange(seq0, seq0 + n, dtype=np.int64) & 0xFFFFFFFF).astype("<u4")
        recs[:, 11:15] = seq.view(np.uint8).reshape(n, 4)
        t8 = np.ascontiguousarray(t_ns, dtype="<i8").view(np.uint8).reshape(n, 8)
        recs[:, 15:23] = t8
        recs[:, 23:31] = t8
        recs[:, 31:] = bodies
        t64 = np.asarray(t_ns, dtype=np.int64)
        a = 0
        while a < n:
            room = self._chunk_size - self._chunk_len
            b = min(n, a + max(1, room // rec_len + 1))  # just past chunk_size, like add_message
            off = self._chunk_len
            self._parts.append(recs[a:b].tobytes())
            pairs = np.empty((b - a, 2), np.int64)
            pairs[:, 0] = t64[a:b]
            pairs[:, 1] = off + rec_len * np.arange(b - a, dtype=np.int64)
            idx = self._chunk_index.get(cid)
            if idx is None:
                idx = self._chunk_index[cid] = []
            idx.append(pairs)
            self._chunk_len = off + rec_len * (b - a)
            a = b
            if self._chunk_len > self._chunk_size:
                self.close_chunk()

    def close_chunk(self) -> None:
        """Compress and write the open chunk and its message indexes (no-op when empty; with the
        background thread: hand it over, waiting while :data:`MAX_PENDING` are queued)."""
        if not self._parts:
            return
        import numpy as np

        raw = b"".join(self._parts)
        n = 0
        t0 = t1 = None
        pairs_of: dict[int, Any] = {}
        for cid, segments in self._chunk_index.items():
            # (log_time, offset) pairs in the order written: flat lists (one message at a time)
            # and (k, 2) arrays (batches)
            pairs = np.concatenate(
                [
                    np.asarray(sg, dtype=np.int64).reshape(-1, 2)
                    for sg in segments
                    if len(sg)  # type: ignore[arg-type]
                ]
            )
            pairs_of[cid] = pairs
            k = len(pairs)
            n += k
            self.channel_message_counts[cid] += k
            lo, hi = int(pairs[:, 0].min()), int(pairs[:, 0].max())
            t0 = lo if t0 is None or lo < t0 else t0
            t1 = hi if t1 is None or hi > t1 else t1
        t0, t1 = int(t0 or 0), int(t1 or 0)
        if self.message_count == 0:
            self.t_start, self.t_end = t0, t1
        else:
            self.t_start = min(self.t_start, t0)
            self.t_end = max(self.t_end, t1)
        self.message_count += n
        self.chunk_count += 1
        self._parts = []
        self._chunk_len = 0
        self._chunk_index = {}
        if self._pool is None:
            self._write_chunk(raw, pairs_of, t0, t1)
        else:
            self.drain(self.MAX_PENDING - 1)
            self._pending.append(self._pool.submit(self._write_chunk, raw, pairs_of, t0, t1))

    def _write_chunk(self, raw: bytes, pairs_of: dict[int, Any], t0: int, t1: int) -> None:
        """Compress and write one chunk (records ``raw``, message start and end times ``t0``,
        ``t1``) and its message indexes (``pairs_of``: channel -> (k, 2) log times and offsets)."""
        import zlib

        from mcap.data_stream import RecordBuilder
        from mcap.records import Chunk, ChunkIndex

        comp = self._compress(raw) if self._compress is not None else raw
        chunk = Chunk(
            compression=self._compression if self._compress is not None else "",
            data=comp,
            message_start_time=t0,
            message_end_time=t1,
            uncompressed_crc=zlib.crc32(raw),
            uncompressed_size=len(raw),
        )
        start = self._fh.tell()
        rb = RecordBuilder()  # its own builder: this may run in the background thread
        chunk.write(rb)
        data = rb.end()
        self._fh.write(data)
        length = len(data)
        offsets: dict[int, int] = {}
        pos = start + length
        index_parts = []
        for cid, pairs in pairs_of.items():
            # MessageIndex record, packed here: opcode 0x04, length, channel id, byte length of the
            # (log_time, offset) pairs, the pairs (the mcap class writes them one call at a time)
            body = pairs.astype("<u8").tobytes()
            offsets[cid] = pos
            rec = struct.pack("<BQHI", _OP_MESSAGE_INDEX, 6 + len(body), cid, len(body)) + body
            index_parts.append(rec)
            pos += len(rec)
        index = b"".join(index_parts)
        self._fh.write(index)
        index_len = len(index)
        self._chunk_indexes.append(
            ChunkIndex(
                message_start_time=t0,
                message_end_time=t1,
                chunk_start_offset=start,
                chunk_length=length,
                message_index_offsets=offsets,
                message_index_length=index_len,
                compression=chunk.compression,
                compressed_size=len(comp),
                uncompressed_size=len(raw),
            )
        )

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        from mcap.records import Metadata, MetadataIndex

        self.drain()
        offset = self._fh.tell()
        Metadata(name=name, metadata=data).write(self._rb)
        length = self._emit()
        self._metadata_indexes.append(MetadataIndex(offset=offset, length=length, name=name))

    def add_attachment(
        self, create_time: int, log_time: int, name: str, media_type: str, data: bytes
    ) -> None:
        from mcap.records import Attachment as McapAttachment
        from mcap.records import AttachmentIndex

        self.drain()
        offset = self._fh.tell()
        McapAttachment(
            create_time=create_time, log_time=log_time, name=name, media_type=media_type, data=data
        ).write(self._rb)
        length = self._emit()
        self._attachment_indexes.append(
            AttachmentIndex(
                offset=offset,
                length=length,
                create_time=create_time,
                log_time=log_time,
                data_size=len(data),
                name=name,
                media_type=media_type,
            )
        )

    def finish(self) -> None:
        """Close the open chunk, write DataEnd, the summary section, the footer and the magic."""
        import zlib

        from mcap.data_stream import RecordBuilder
        from mcap.opcode import Opcode
        from mcap.records import DataEnd, Footer, Statistics, SummaryOffset

        self.close_chunk()
        self.shutdown()
        DataEnd(data_section_crc=0).write(self._rb)
        self._emit()
        summary_start = self._fh.tell()
        sb = RecordBuilder()
        offsets: list[Any] = []

        def group(opcode: int, records: Iterable[Any]) -> None:
            g0 = sb.count
            for r in records:
                r.write(sb)
            offsets.append(
                SummaryOffset(
                    group_opcode=opcode, group_start=summary_start + g0, group_length=sb.count - g0
                )
            )

        group(Opcode.SCHEMA, self._schemas.values())
        group(Opcode.CHANNEL, self._channels.values())
        stats = Statistics(
            attachment_count=len(self._attachment_indexes),
            channel_count=len(self._channels),
            channel_message_counts={k: v for k, v in self.channel_message_counts.items() if v},
            chunk_count=self.chunk_count,
            message_count=self.message_count,
            message_end_time=self.t_end,
            message_start_time=self.t_start,
            metadata_count=len(self._metadata_indexes),
            schema_count=len(self._schemas),
        )
        group(Opcode.STATISTICS, [stats])
        group(Opcode.CHUNK_INDEX, self._chunk_indexes)
        group(Opcode.ATTACHMENT_INDEX, self._attachment_indexes)
        group(Opcode.METADATA_INDEX, self._metadata_indexes)
        summary_offset_start = summary_start + sb.count
        for o in offsets:
            o.write(sb)
        summary = sb.end()
        crc = zlib.crc32(summary)
        crc = zlib.crc32(
            struct.pack("<BQQQ", Opcode.FOOTER, 20, summary_start, summary_offset_start), crc
        )
        self._fh.write(summary)
        Footer(
            summary_start=summary_start, summary_offset_start=summary_offset_start, summary_crc=crc
        ).write(self._rb)
        self._emit()
        self._fh.write(_MAGIC)


# -------------------------------------------------------------------------------------------------
# writer


@dataclass
class _BlockStream:
    """The writer's state of one column-block stream: the samples not yet written, the view's
    channel, its last 20 ms bin and message count, and the integer fields (a missing value, NaN in
    the block, is left out of a view message rather than written as null)."""

    buf: column_blocks.BlockBuffer
    view_cid: int | None
    ints: set[str]
    last_bin: int = -1
    view_count: int = 0
    #: %-formats of the view's rows, by (column, is float) names
    formats: dict[tuple[tuple[str, bool], ...], str] = field(default_factory=dict)


class McapRunWriter:
    """An MCAP run file being written: channels per stream, bounded chunks, fsync, never overwrite.

    Parameters
    ----------
    path:
        Output file; it must not exist (opened with exclusive create).
    chunk_size:
        A chunk is closed when its uncompressed size exceeds this many bytes ...
    flush_interval_s:
        ... or when it is older than this (checked by :meth:`maybe_flush`); each flush is fsynced.
    compression:
        ``"zstd"``, ``"lz4"`` or ``"none"``.
    background_compression:
        Compress and write the chunks in a thread while the caller goes on (bulk writers such as
        ``cdpr import``, whose parsing then runs beside the compression on another core); a flush
        still returns only once its chunk is with the OS.
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        chunk_size: int = 256 * 1024,
        flush_interval_s: float = 0.25,
        compression: str = "zstd",
        background_compression: bool = False,
    ) -> None:
        if compression not in ("zstd", "lz4", "none"):
            raise InputError(f"compression must be zstd, lz4 or none, got {compression!r}")
        if chunk_size < 1024:
            raise InputError(f"chunk_size must be >= 1024 bytes, got {chunk_size}")
        if not flush_interval_s > 0:
            raise InputError(f"flush_interval_s must be > 0, got {flush_interval_s}")
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            self._fh = open(self.path, "xb")  # noqa: SIM115 - closed in finish()
        except FileExistsError:
            raise InputError(f"{self.path}: exists already; a run is never overwritten") from None
        self._writer = _ChunkedWriter(self._fh, chunk_size, compression, background_compression)
        self._chunk_size = chunk_size
        self._writer.start(PROFILE, LIBRARY)
        self.flush_interval_ns = int(flush_interval_s * 1e9)
        self._last_flush_ns = time.monotonic_ns()
        self._channels: dict[str, int] = {}
        self._codecs: dict[str, Callable[[Reading], Any]] = {}
        self._frame_encoders: dict[str, Callable[[Any], FrameRecords]] = {}
        self._blocks: dict[str, _BlockStream] = {}  # column-block streams (column_blocks)
        self._block_rows: dict[str, Callable[[Sequence[Reading]], Any]] = {}  # layouts' readings
        #: samples written per stream (a block stream's samples, not its block messages)
        self.counts: dict[str, int] = {}
        self.flushes = 0
        self.fsyncs = 0
        self._fsync_wanted = threading.Event()
        self._fsync_stop = False
        self._fsync_thread = threading.Thread(
            target=self._fsync_loop, name="mcap-fsync", daemon=True
        )
        self._fsync_thread.start()
        self.finished = False

    # channels ------------------------------------------------------------------------------
    def add_stream(
        self,
        stream: str,
        description: StreamDescription | None = None,
        blocks: bool | None = None,
    ) -> int:
        """Register ``/<stream>`` (idempotent); returns its channel id.  ``blocks``: store the
        samples as column blocks (:mod:`cdpr.daq.column_blocks`); None: when the description is
        flat numeric at :data:`~cdpr.daq.column_blocks.MIN_RATE_HZ` or more (True also needs a flat
        numeric description, whatever its rate: ``cdpr import`` of a log of unknown rate)."""
        if stream in self._channels:
            return self._channels[stream]
        codec = codec_for(stream, description)
        if blocks is not False and description is not None and codec.block_layout is not None:
            return self._add_block_stream(stream, description, codec, codec.block_layout)
        if (
            blocks is not False
            and description is not None
            and codec.schema_name == f"cdpr.{stream}"
            and column_blocks.uses_blocks(description, any_rate=bool(blocks))
        ):
            return self._add_block_stream(stream, description, codec)
        schema_id = self._writer.register_schema(
            codec.schema_name,
            "jsonschema",
            json.dumps(codec.schema, separators=(",", ":")).encode(),
        )
        meta = {"stream": stream}
        if description is not None:
            meta["rate_hz"] = repr(float(description.rate_hz))
            units = {k: f.unit for k, f in description.fields.items() if f.unit}
            if units:
                meta["units"] = json.dumps(units, separators=(",", ":"))
        cid = self._writer.register_channel(topic_of(stream), "json", schema_id, meta)
        self._channels[stream] = cid
        self._codecs[stream] = codec.encode
        if codec.encode_frames is not None:
            self._frame_encoders[stream] = codec.encode_frames
        self.counts[stream] = 0
        return cid

    def _add_block_stream(
        self,
        stream: str,
        description: StreamDescription,
        codec: StreamCodec,
        layout: str | None = None,
    ) -> int:
        """A high-rate flat numeric stream: column blocks on ``/<stream>`` and the per-sample view
        on ``/<stream>/view`` (:mod:`cdpr.daq.column_blocks`); with a ``layout`` (the codec's
        ``block_layout``: columns its module defines, written with :meth:`write_columns`), the
        blocks alone."""
        w = self._writer
        meta = {"stream": stream, "rate_hz": repr(float(description.rate_hz))}
        units = {k: f.unit for k, f in description.fields.items() if f.unit}
        if units:
            meta["units"] = json.dumps(units, separators=(",", ":"))
        sid = w.register_schema(
            column_blocks.BLOCK_SCHEMA_NAME,
            "jsonschema",
            json.dumps(column_blocks.block_schema(stream, description)).encode(),
        )
        block_meta = column_blocks.channel_metadata(description)
        if layout is not None:  # the per-sample fields as the layout's module reads them back
            fields = {k: [f.dtype, f.unit] for k, f in description.fields.items()}
            block_meta = {**block_meta, "layout": layout, "fields": json.dumps(fields)}
        cid = w.register_channel(topic_of(stream), "json", sid, {**meta, **block_meta})
        self._channels[stream] = cid
        self._codecs[stream] = codec.encode
        self.counts[stream] = 0
        if layout is not None:
            if codec.block_rows is not None:
                self._block_rows[stream] = codec.block_rows
            self._blocks[stream] = _BlockStream(
                column_blocks.BlockBuffer(column_blocks.MAX_BLOCK_SAMPLES), None, set()
            )
            return cid
        period = column_blocks.VIEW_PERIOD_NS
        vsid = w.register_schema(
            codec.schema_name,
            "jsonschema",
            json.dumps(codec.schema, separators=(",", ":")).encode(),
        )
        vmeta = {**meta, "view_of": topic_of(stream), "view_period_ns": str(period)}
        vmeta["rate_hz"] = repr(min(float(description.rate_hz), 1e9 / period))
        vcid = w.register_channel(topic_of(stream) + "/view", "json", vsid, vmeta)
        # a block holds at most about one chunk of samples (so chunk_size bounds a block too)
        ncols = len(description.fields) + 2
        self._blocks[stream] = _BlockStream(
            column_blocks.BlockBuffer(
                max(1, min(column_blocks.MAX_BLOCK_SAMPLES, self._chunk_size // (8 * ncols)))
            ),
            vcid,
            column_blocks.int_fields(description),
        )
        return cid

    @property
    def streams(self) -> list[str]:
        return list(self._channels)

    def _emit_block(self, stream: str) -> None:
        """Write the buffered samples of a block stream as one block (split at
        :data:`~cdpr.daq.column_blocks.MAX_BLOCK_SAMPLES`) and their per-sample view messages."""
        import numpy as np

        bs = self._blocks[stream]
        buf = bs.buf
        got = buf.take()
        if got is None:
            return
        t_all, cols_all = got
        stored = {k: column_blocks.narrow(v) for k, v in cols_all.items()}  # the same values
        cid = self._channels[stream]
        add = self._writer.add_message
        step = buf.max_samples
        for a in range(0, len(t_all), step):
            t = t_all[a : a + step]
            cols = {k: v[a : a + step] for k, v in stored.items()}
            body = column_blocks.encode_block(t, cols, buf.written, buf.values)
            add(cid, int(t[-1]), body, int(t[0]), buf.messages)
            buf.messages += 1
            buf.written += len(t)
        if bs.view_cid is None:
            return
        # the view: the first sample in each VIEW_PERIOD_NS bin of time
        bins = t_all // column_blocks.VIEW_PERIOD_NS
        pick = np.flatnonzero(np.diff(bins, prepend=bs.last_bin) != 0)
        bs.last_bin = int(bins[-1])
        if len(pick):
            self._emit_view(bs, t_all[pick], {k: v[pick] for k, v in cols_all.items()})

    def _emit_view(self, bs: _BlockStream, t: Any, cols: dict[str, Any]) -> None:
        """The view messages of samples at times ``t`` (``cols``: their values): rows of finite
        numbers through a %-format of the columns (``%r`` of a float is what JSON writes), the
        others as dicts (a NaN in an integer field left out: missing, not null)."""
        import numpy as np

        add = self._writer.add_message
        names = list(cols)
        floats = [n for n in names if cols[n].dtype.kind == "f"]
        finite = np.ones(len(t), bool)
        for n in floats:
            finite &= np.isfinite(cols[n])
        key = tuple((n, n in floats) for n in names)
        fmt = bs.formats.get(key)
        if fmt is None:
            quoted = [json.dumps(n).replace("%", "%%") for n, _ in key]
            fmt = bs.formats[key] = (
                "{"
                + ",".join(
                    f"{q}:%r" if f else f"{q}:%d" for q, (_, f) in zip(quoted, key, strict=True)
                )
                + "}"
            )
        rows = [cols[n].tolist() for n in names]
        ts = t.tolist()
        k = bs.view_count
        for j, (ti, ok, row) in enumerate(
            zip(ts, finite.tolist(), zip(*rows, strict=True), strict=True)
        ):
            if ok:
                body = (fmt % row).encode()
            else:
                body = encode_json(
                    {
                        n: v
                        for n, v in zip(names, row, strict=True)
                        if not (n in bs.ints and v != v)  # NaN: missing, not null
                    }
                )
            add(bs.view_cid, ti, body, ti, k + j)
        bs.view_count = k + len(ts)

    def _emit_blocks(self) -> None:
        for stream, bs in self._blocks.items():
            if len(bs.buf):
                self._emit_block(stream)

    def write_columns(
        self,
        stream: str,
        t_ns: Any,
        columns: Mapping[str, Any],
        status: Any = 0,
        values: Mapping[str, Any] | None = None,
    ) -> int:
        """Write samples of ``stream`` given as columns (``t_ns`` (n,) int ns; each column (n,)
        numbers, NaN for missing; ``status`` (n,) or one int): the bulk path of ``cdpr import`` and
        the benchmarks.  A block stream takes the arrays as they are (``values``: the tables of
        indexed columns, :mod:`cdpr.daq.column_blocks`); any other stream gets one message per
        sample.  Returns how many samples."""
        import numpy as np

        t_ns = np.asarray(t_ns, np.int64)
        if stream not in self._channels:
            self.add_stream(stream, None)
        bs = self._blocks.get(stream)
        if bs is not None:
            buf = bs.buf
            buf.add_columns(t_ns, columns, status, values)
            self.counts[stream] += len(t_ns)
            if len(buf) >= buf.max_samples:
                self._emit_block(stream)
            return len(t_ns)
        if values:
            raise InputError(f"{stream}: indexed columns need a column-block stream")
        st = np.broadcast_to(np.asarray(status, np.int64), t_ns.shape)
        names = list(columns)
        arrays = [np.asarray(columns[k]) for k in names]
        return self.write_many(
            Reading(stream, int(t_ns[i]), {k: a[i].item() for k, a in zip(names, arrays, strict=True)},
                    int(st[i]))
            for i in range(len(t_ns))
        )  # fmt: skip

    # data ----------------------------------------------------------------------------------
    def write(self, reading: Reading) -> None:
        """Write one reading (its stream is registered on first use if it was not declared)."""
        self.write_many((reading,))

    def write_many(self, readings: Iterable[Reading]) -> int:
        """Write readings in order (the recorder's hot loop); returns how many.

        A registered batch type (:func:`register_frame_batch_type`: the CAN sources'
        :class:`~cdpr.daq.can_raw.CanFrameBatch`) has its frames written at once: as a frame
        block (its ``frame_block()``) on a block stream, else by its stream codec's
        ``encode_frames``; its other readings (decoded tensions) follow."""
        if is_frame_batch(readings):
            return self._write_frame_batch(readings)
        channels = self._channels
        codecs = self._codecs
        counts = self.counts
        add = self._writer.add_message
        blocks = self._blocks
        n = 0
        for r in readings:
            stream = r.stream
            cid = channels.get(stream)
            if cid is None:
                cid = self.add_stream(stream, None)
            bs = blocks.get(stream)
            if bs is not None and stream in self._block_rows:  # a layout's reading: its columns
                self.write_columns(stream, *self._block_rows[stream]([r]))
                n += 1
                continue
            if bs is not None:
                buf = bs.buf
                buf.add_reading(r.t_ns, r.values, r.status)
                counts[stream] += 1
                if buf.n >= buf.max_samples:
                    self._emit_block(stream)
                n += 1
                continue
            body = codecs[stream](r)
            data = body if type(body) is bytes else encode_json(body)
            k = counts[stream]
            add(cid, r.t_ns, data, r.t_ns, k)
            counts[stream] = k + 1
            n += 1
        return n

    def _write_frame_batch(self, batch: Any) -> int:
        stream = batch.stream
        msgs = batch.messages
        n = len(batch.t_ns)
        if n:
            if stream not in self._channels:
                self.add_stream(stream, None)
            if stream in self._blocks:  # a layout's block stream: the batch gives its columns
                self.write_columns(stream, *batch.frame_block())
            else:
                encode_frames = self._frame_encoders.get(stream)
                if encode_frames is None:  # another codec for this stream: reading by reading
                    return self.write_many(list(batch))
                self.write_records(stream, batch.t_ns[:n], encode_frames(msgs), batch.frame_reading)
        others = batch.others
        if others:
            self.write_many([r for _, r in others])
        return n + len(others)

    def write_records(
        self,
        stream: str,
        t_ns: Any,
        records: FrameRecords,
        reading_of: Callable[[int], Reading],
    ) -> int:
        """Write ``len(t_ns)`` messages of ``stream`` in order: those with ``records.ok`` from the
        preformatted ``records.bodies`` (a codec's ``encode_frames``), the others encoded one by one
        from ``reading_of(i)``.  Returns how many."""
        import numpy as np

        t_ns = np.asarray(t_ns, dtype=np.int64)
        n = len(t_ns)
        if not n:
            return 0
        cid = self._channels.get(stream)
        if cid is None:
            cid = self.add_stream(stream, None)
        if stream in self._blocks:
            raise InputError(f"{stream}: a column-block stream takes write_columns, not records")
        k0 = self.counts[stream]
        w = self._writer
        if len(records.bodies) == n:
            w.add_messages(cid, t_ns, records.bodies, k0)
        else:
            # runs of formatted frames, the others (error frames, other lengths) one by one
            encode = self._codecs[stream]
            bad = np.flatnonzero(~np.asarray(records.ok)).tolist()
            a = j = 0
            for i in [*bad, n]:
                if i > a:
                    w.add_messages(cid, t_ns[a:i], records.bodies[j : j + i - a], k0 + a)
                    j += i - a
                if i < n:
                    r = reading_of(i)
                    body = encode(r)
                    data = body if type(body) is bytes else encode_json(body)
                    w.add_message(cid, r.t_ns, data, r.t_ns, k0 + i)
                a = i + 1
        self.counts[stream] = k0 + n
        return n

    def maybe_flush(self) -> bool:
        """Close the open chunk and fsync if it is older than the flush interval."""
        if time.monotonic_ns() - self._last_flush_ns >= self.flush_interval_ns:
            self.flush()
            return True
        return False

    def flush(self) -> None:
        """Close the open chunk (if any) and hand it to the OS (it now survives the process being
        killed), then have it fsynced (durable across a power cut) by the fsync thread, so the
        writer does not wait for the disk."""
        self._emit_blocks()
        self._writer.close_chunk()
        self._writer.drain()
        self._fh.flush()
        self._fsync_wanted.set()
        self._last_flush_ns = time.monotonic_ns()
        self.flushes += 1

    def _fsync_loop(self) -> None:
        fd = self._fh.fileno()
        while True:
            self._fsync_wanted.wait()
            self._fsync_wanted.clear()
            if self._fsync_stop:
                return
            try:
                os.fsync(fd)
                self.fsyncs += 1
            except OSError:  # reported by the final, synchronous fsync in finish()
                return

    def add_metadata(self, name: str, data: Mapping[str, Any]) -> None:
        """A metadata record; values are converted to strings (non-strings as JSON)."""
        self._writer.add_metadata(
            name, {str(k): v if isinstance(v, str) else json.dumps(v) for k, v in data.items()}
        )

    def add_attachment(self, name: str, data: bytes, media_type: str = "text/plain") -> None:
        """Embed a file (rig, calibration, config) in the run."""
        now = time.time_ns()
        self._writer.add_attachment(now, now, name, media_type, data)

    def finish(self) -> None:
        """Write the summary section and footer, fsync and close; idempotent."""
        if self.finished:
            return
        self.finished = True
        try:
            self._emit_blocks()
            self._writer.finish()
            self._fh.flush()
            os.fsync(self._fh.fileno())
        finally:
            try:
                self._writer.shutdown()  # after an error: the chunks already handed over
            finally:
                self._fsync_stop = True
                self._fsync_wanted.set()
                self._fsync_thread.join(timeout=30.0)
                self._fh.close()
