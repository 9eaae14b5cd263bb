"""Run files in MCAP, the writing side: :class:`McapRunWriter`, the recorder's writer, which ties
the parts of the job together (each in a module of its own):

- :mod:`cdpr.daq.mcap_codecs`: the stream codecs (schemas and encoders) and their registry
  (:func:`register_stream_codec`, :func:`codec_for`), re-exported here;
- :mod:`cdpr.daq.mcap_chunks`: the chunk writer (:class:`~cdpr.daq.mcap_chunks.ChunkedWriter`:
  records, hand-packed messages, chunk compression, summary);
- :mod:`cdpr.daq.mcap_blocks`: high-rate streams as column blocks and their per-sample view;
- :mod:`cdpr.daq.mcap_fsync`: the fsync thread.

Layout of a run file (see ``docs/recording.md``):

- one channel per stream, topic ``/<stream>``, message encoding ``json``, schema encoding
  ``jsonschema``; a message's ``log_time`` is the reading's ``t_ns`` (host time of reception, ns since
  the Unix epoch) and its JSON body holds the reading's values (flat numeric fields, so a plot panel
  graphs them) plus ``status``; Foxglove's well-known schemas where one exists (the codecs);
- metadata records (``run`` at the start, ``run_end`` at the end) and attachments (rig file,
  calibration files, config file), so a run file is self-contained.

The python ``mcap`` writer closes a chunk only when it outgrows ``chunk_size``;
:class:`McapRunWriter` also closes it when it is older than ``flush_interval_s`` and fsyncs the file,
so a killed recorder loses at most about one flush interval of data.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from cdpr.analysis.errors import InputError

from . import column_blocks, mcap_blocks
from .mcap_blocks import BlockStream
from .mcap_chunks import ChunkedWriter
from .mcap_codecs import (  # the codecs' public names, imported from here by drivers and tests
    LOG_LEVELS,
    FrameRecords,
    StreamCodec,
    codec_for,
    encode_json,
    flat_codec,
    is_frame_batch,
    ns_to_time,
    register_frame_batch_type,
    register_stream_codec,
    topic_of,
)
from .mcap_fsync import FsyncThread
from .source import Reading, StreamDescription

__all__ = [
    "LIBRARY",
    "LOG_LEVELS",
    "PROFILE",
    "FrameRecords",
    "McapRunWriter",
    "StreamCodec",
    "codec_for",
    "encode_json",
    "flat_codec",
    "is_frame_batch",
    "ns_to_time",
    "register_frame_batch_type",
    "register_stream_codec",
    "topic_of",
]

PROFILE = ""
LIBRARY = "cdpr-recorder"


def _channel_meta(
    name: str,
    description: StreamDescription | None,
    extra: Mapping[str, str] | None = None,
    fields: Mapping[str, Any] | None = None,
) -> dict[str, str]:
    """A channel's metadata: ``stream`` = ``name``, the ``extra`` keys, then from the description
    ``rate_hz`` and ``units`` (JSON map field -> unit; ``fields``: only these fields)."""
    meta = {"stream": name, **(extra or {})}
    if description is not None:
        meta["rate_hz"] = repr(float(description.rate_hz))
        units = {
            k: f.unit
            for k, f in description.fields.items()
            if f.unit and (fields is None or k in fields)
        }
        if units:
            meta["units"] = json.dumps(units, separators=(",", ":"))
    return meta


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
        self._writer = ChunkedWriter(self._fh, chunk_size, compression, background_compression)
        self._chunk_size = chunk_size
        self._writer.start(PROFILE, LIBRARY)
        self.flush_interval_ns = int(flush_interval_s * 1e9)
        self._last_flush_ns = time.monotonic_ns()
        self._channels: dict[str, int] = {}
        self._codecs: dict[str, Callable[[Reading], Any]] = {}
        self._frame_encoders: dict[str, Callable[[Any], FrameRecords]] = {}
        self._blocks: dict[str, BlockStream] = {}  # column-block streams (mcap_blocks)
        #: a layout's block stream: its readings -> columns (StreamCodec.block_rows)
        self._block_rows: dict[str, Callable[[Sequence[Reading]], Any]] = {}
        #: stream -> channel id and encoder of its ``/<stream>_status`` (StreamCodec.status)
        self._status: dict[str, tuple[int, Callable[[Reading], Any]]] = {}
        #: samples written per stream (a block stream's samples, not its block messages)
        self.counts: dict[str, int] = {}
        self.flushes = 0
        self._fsync = FsyncThread(self._fh)
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
        cid = self._register(topic_of(stream), codec, _channel_meta(stream, description))
        self._channels[stream] = cid
        self._codecs[stream] = codec.encode
        if codec.encode_frames is not None:
            self._frame_encoders[stream] = codec.encode_frames
        if codec.status is not None:
            self._add_status_channel(stream, description, codec.status)
        self.counts[stream] = 0
        return cid

    def _register(self, topic: str, codec: StreamCodec, meta: dict[str, str]) -> int:
        """Register the codec's schema and a JSON channel ``topic`` with ``meta``; its id."""
        sid = self._writer.register_schema(
            codec.schema_name,
            "jsonschema",
            json.dumps(codec.schema, separators=(",", ":")).encode(),
        )
        return self._writer.register_channel(topic, "json", sid, meta)

    def _add_status_channel(
        self, stream: str, description: StreamDescription | None, codec: StreamCodec
    ) -> None:
        """``/<stream>_status``: one message per reading of ``stream`` (:attr:`StreamCodec.status`),
        channel metadata ``status_of`` = ``/<stream>``."""
        meta = _channel_meta(
            f"{stream}_status",
            description,
            {"status_of": topic_of(stream)},
            codec.schema.get("properties", {}),
        )
        cid = self._register(topic_of(stream) + "_status", codec, meta)
        self._status[stream] = (cid, codec.encode)

    def _add_block_stream(
        self,
        stream: str,
        description: StreamDescription,
        codec: StreamCodec,
        layout: str | None = None,
    ) -> int:
        """A high-rate flat numeric stream as column blocks (:func:`mcap_blocks.add_block_stream`:
        ``/<stream>`` and its view ``/<stream>/view``, or with a ``layout`` the blocks alone)."""
        bs = mcap_blocks.add_block_stream(
            self._writer,
            stream,
            description,
            codec,
            _channel_meta(stream, description),
            self._chunk_size,
            layout,
        )
        self._channels[stream] = bs.cid
        self._codecs[stream] = codec.encode
        self.counts[stream] = 0
        self._blocks[stream] = bs
        if layout is not None and codec.block_rows is not None:
            self._block_rows[stream] = codec.block_rows
        return bs.cid

    @property
    def streams(self) -> list[str]:
        return list(self._channels)

    def _emit_blocks(self) -> None:
        for bs in self._blocks.values():
            if len(bs.buf):
                mcap_blocks.emit_block(self._writer, bs)

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
                mcap_blocks.emit_block(self._writer, bs)
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
        status = self._status
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
                    mcap_blocks.emit_block(self._writer, bs)
                n += 1
                continue
            body = codecs[stream](r)
            k = counts[stream]
            if body is not None:  # None: no message on this channel (a frame without a pose)
                add(cid, r.t_ns, body if type(body) is bytes else encode_json(body), r.t_ns, k)
            if stream in status:  # /<stream>_status: every reading; sequence = the reading's
                scid, encode_status = status[stream]
                add(scid, r.t_ns, encode_json(encode_status(r)), r.t_ns, k)
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
        self._fsync.request()
        self._last_flush_ns = time.monotonic_ns()
        self.flushes += 1

    @property
    def fsyncs(self) -> int:
        """Background fsyncs done so far."""
        return self._fsync.count

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
                self._fsync.stop()
                self._fh.close()
