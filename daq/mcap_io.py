"""Run files in MCAP, the raw side: the streaming reader (:func:`read_run`, every message as a
dict, for tests and tools that look at message bodies) and truncated-file recovery
(:func:`recover_run`).  The columnar reader is :func:`cdpr.daq.run_reader.open_run`; the writer and
codecs are in :mod:`cdpr.daq.mcap_writer` (re-exported here for existing imports).
"""

from __future__ import annotations

import json
import os
import struct
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cdpr.analysis.errors import ConfigError, InputError

from .mcap_writer import (  # noqa: F401  (re-exported: the writer's public names)
    LIBRARY,
    LOG_LEVELS,
    PROFILE,
    FrameRecords,
    McapRunWriter,
    StreamCodec,
    codec_for,
    encode_json,
    flat_codec,
    ns_to_time,
    register_frame_batch_type,
    register_stream_codec,
    topic_of,
)

# -------------------------------------------------------------------------------------------------
# reader


@dataclass
class ChannelInfo:
    """A channel of a run file."""

    id: int
    topic: str
    schema_name: str
    message_encoding: str
    metadata: dict[str, str]
    schema: dict[str, Any] | None = None


@dataclass
class RunContents:
    """Everything in a run file, as the mcap reader sees it.

    messages: topic -> list of (log_time_ns, decoded JSON body).
    complete: the file ends with a valid footer (False for a truncated file read in recovery mode).
    """

    channels: dict[str, ChannelInfo] = field(default_factory=dict)
    messages: dict[str, list[tuple[int, dict[str, Any]]]] = field(default_factory=dict)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    attachments: dict[str, tuple[str, bytes]] = field(default_factory=dict)
    complete: bool = False
    error: str | None = None


def _check_file(path: str | os.PathLike[str]) -> Path:
    p = Path(path)
    if not p.is_file():
        raise ConfigError(str(p), "", "file not found")
    with p.open("rb") as fh:
        magic = fh.read(8)
    if magic != b"\x89MCAP0\r\n":
        raise ConfigError(str(p), "", "not an MCAP file (bad magic bytes)")
    return p


def iter_records(path: str | os.PathLike[str]) -> Iterator[Any]:
    """Every record of an MCAP file in order (chunks expanded), stopping quietly at a truncation or
    corruption; the reason is available from :func:`read_run` (``error``)."""
    yield from _iter_records(Path(path), [])


def _iter_records(p: Path, errors: list[str]) -> Iterator[Any]:
    from mcap.exceptions import McapError
    from mcap.stream_reader import StreamReader

    with p.open("rb") as fh:
        reader = StreamReader(fh, validate_crcs=True)
        try:
            yield from reader.records
        except (McapError, struct.error, ValueError, EOFError) as exc:
            # McapError: EndOfFile, bad magic, record too long; struct.error: a record header cut
            # short; ValueError: CRC mismatch or a zstd frame cut short.
            errors.append(f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__)


def read_run(path: str | os.PathLike[str], *, decode: bool = True) -> RunContents:
    """Read a run file with the streaming reader: every record up to the end or the first damaged
    one (a truncated file yields every complete chunk).  ``decode=False`` keeps message bodies as
    raw bytes (under key ``"_raw"``), which is faster."""
    from mcap.records import Attachment, Channel, Footer, Message, Metadata, Schema

    p = _check_file(path)
    out = RunContents()
    schemas: dict[int, Any] = {}
    by_id: dict[int, str] = {}
    errors: list[str] = []
    loads = json.loads
    for rec in _iter_records(p, errors):
        if isinstance(rec, Message):
            topic = by_id.get(rec.channel_id)
            if topic is None:
                continue
            body = loads(rec.data) if decode else {"_raw": rec.data}
            out.messages[topic].append((rec.log_time, body))
        elif isinstance(rec, Schema):
            schemas[rec.id] = rec
        elif isinstance(rec, Channel):
            if rec.id in by_id:
                continue
            sch = schemas.get(rec.schema_id)
            schema_json = None
            if sch is not None and sch.encoding == "jsonschema":
                try:
                    schema_json = json.loads(sch.data)
                except ValueError:
                    schema_json = None
            out.channels[rec.topic] = ChannelInfo(
                rec.id,
                rec.topic,
                sch.name if sch is not None else "",
                rec.message_encoding,
                dict(rec.metadata),
                schema_json,
            )
            by_id[rec.id] = rec.topic
            out.messages.setdefault(rec.topic, [])
        elif isinstance(rec, Metadata):
            out.metadata[rec.name] = dict(rec.metadata)
        elif isinstance(rec, Attachment):
            out.attachments[rec.name] = (rec.media_type, bytes(rec.data))
        elif isinstance(rec, Footer):
            out.complete = True
    out.error = errors[0] if errors else None
    return out


def recover_run(
    path: str | os.PathLike[str], out_path: str | os.PathLike[str] | None = None
) -> tuple[Path, RunContents]:
    """Salvage a truncated or damaged run file into ``<run>.recovered.mcap``.

    Every complete chunk (and every schema, channel, metadata record and attachment before the
    damage) is copied into a new, finished file; the original is left untouched.  Returns the new
    path and what was read.  Refuses to overwrite an existing output.
    """
    from mcap.records import Attachment, Channel, Footer, Message, Metadata, Schema
    from mcap.writer import CompressionType, Writer

    p = _check_file(path)
    if out_path is None:
        stem = p.name[:-5] if p.name.endswith(".mcap") else p.name
        out_path = p.with_name(stem + ".recovered.mcap")
    q = Path(out_path)
    if q.exists():
        raise InputError(f"{q}: exists already; a run is never overwritten")
    tmp = q.with_name(f".{q.name}.part")
    contents = RunContents()
    errors: list[str] = []
    try:
        with open(tmp, "xb") as fh:
            w = Writer(fh, chunk_size=1024 * 1024, compression=CompressionType.ZSTD)
            w.start(profile=PROFILE, library=LIBRARY + "-recover")
            schema_map: dict[int, int] = {}
            chan_map: dict[int, int] = {}
            pending: dict[int, Any] = {}
            for rec in _iter_records(p, errors):
                if isinstance(rec, Message):
                    cid = chan_map.get(rec.channel_id)
                    if cid is None:
                        continue
                    w.add_message(cid, rec.log_time, rec.data, rec.publish_time, rec.sequence)
                    topic = pending[rec.channel_id].topic
                    contents.messages.setdefault(topic, []).append((rec.log_time, {}))
                elif isinstance(rec, Schema) and rec.id not in schema_map:
                    schema_map[rec.id] = w.register_schema(rec.name, rec.encoding, rec.data)
                elif isinstance(rec, Channel) and rec.id not in chan_map:
                    chan_map[rec.id] = w.register_channel(
                        rec.topic,
                        rec.message_encoding,
                        schema_map.get(rec.schema_id, 0),
                        dict(rec.metadata),
                    )
                    pending[rec.id] = rec
                    contents.messages.setdefault(rec.topic, [])
                elif isinstance(rec, Metadata):
                    w.add_metadata(rec.name, dict(rec.metadata))
                    contents.metadata[rec.name] = dict(rec.metadata)
                elif isinstance(rec, Attachment):
                    w.add_attachment(
                        rec.create_time, rec.log_time, rec.name, rec.media_type, rec.data
                    )
                    contents.attachments[rec.name] = (rec.media_type, b"")
                elif isinstance(rec, Footer):
                    contents.complete = True
            w.add_metadata(
                "recovery",
                {
                    "source_file": p.name,
                    "source_complete": str(contents.complete).lower(),
                    "stopped_at": errors[0] if errors else "end of file",
                    "messages": str(sum(len(v) for v in contents.messages.values())),
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
    contents.error = errors[0] if errors else None
    return q, contents
