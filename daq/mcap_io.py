"""Run files in MCAP, the raw side: the streaming reader (:func:`read_run`, every message as a
dict, for tests and tools that look at message bodies) and truncated-file recovery
(:func:`recover_run`).  The columnar reader is :func:`cdpr.daq.run_reader.open_run`; the writer is
:mod:`cdpr.daq.mcap_writer` (its public names, with the codecs' of :mod:`cdpr.daq.mcap_codecs`,
re-exported here for existing imports).
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cdpr.analysis.errors import ConfigError, InputError

from .column_blocks import STORAGE, decode_blocks
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


def _iter_records(p: Path, errors: list[str]) -> Iterator[Any]:
    from mcap.stream_reader import StreamReader

    with p.open("rb") as fh:
        reader = StreamReader(fh, validate_crcs=True)
        try:
            yield from reader.records
        except Exception as exc:
            # McapError: EndOfFile, bad magic, record too long, CRC mismatch; struct.error: a record
            # header cut short; ValueError: a zstd frame cut short; ZstdError / lz4 RuntimeError: a
            # corrupted frame; UnicodeDecodeError: a damaged name. Any damage ends the read here.
            errors.append(f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__)


def read_run(path: str | os.PathLike[str], *, decode: bool = True) -> RunContents:
    """Read a run file with the streaming reader: every record up to the end or the first damaged
    one (a truncated file yields every complete chunk).  A column-block channel
    (:mod:`cdpr.daq.column_blocks`) gives one ``(t_ns, values)`` per sample.  ``decode=False``
    keeps message bodies as raw bytes (under key ``"_raw"``: one per block message), which is
    faster."""
    from mcap.records import Attachment, Channel, Footer, Message, Metadata, Schema

    p = _check_file(path)
    out = RunContents()
    schemas: dict[int, Any] = {}
    by_id: dict[int, str] = {}
    errors: list[str] = []
    blocked: set[int] = set()  # column-block channels
    frame_blocks: set[int] = set()  # those of raw CAN frames (layout can_frames)
    loads = json.loads
    for rec in _iter_records(p, errors):
        if isinstance(rec, Message):
            topic = by_id.get(rec.channel_id)
            if topic is None:
                continue
            if decode and rec.channel_id in frame_blocks:  # one (t_ns, values) per frame
                out.messages[topic] += _frame_rows(decode_blocks([rec.data], str(p)), p)
                continue
            if decode and rec.channel_id in blocked:  # one (t_ns, values) per sample
                cols = decode_blocks([rec.data], str(p))
                t = cols.pop("t_ns").tolist()
                vals = {k: v.tolist() for k, v in cols.items()}
                out.messages[topic] += [
                    (t[i], {k: v[i] for k, v in vals.items()}) for i in range(len(t))
                ]
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
            if rec.metadata.get("storage") == STORAGE:
                blocked.add(rec.id)
                if rec.metadata.get("layout") == "can_frames":
                    frame_blocks.add(rec.id)
            out.messages.setdefault(rec.topic, [])
        elif isinstance(rec, Metadata):
            out.metadata[rec.name] = dict(rec.metadata)
        elif isinstance(rec, Attachment):
            out.attachments[rec.name] = (rec.media_type, bytes(rec.data))
        elif isinstance(rec, Footer):
            out.complete = True
    out.error = errors[0] if errors else None
    return out


def _frame_rows(cols: dict[str, Any], path: Path) -> list[tuple[int, dict[str, Any]]]:
    from .can_raw import frame_rows

    try:
        return frame_rows(cols)
    except (KeyError, ValueError) as exc:
        raise InputError(f"{path}: a block of CAN frames is malformed ({exc})") from None


def recover_run(
    path: str | os.PathLike[str], out_path: str | os.PathLike[str] | None = None
) -> tuple[Path, RunContents]:
    """Salvage a truncated or damaged run file into ``<run>.recovered.mcap``: every readable chunk,
    before and after damage (skipped chunks are named); see :func:`cdpr.daq.recover.recover_run`."""
    from .recover import recover_run as _recover

    out, contents = _recover(path, out_path)
    return out, contents
